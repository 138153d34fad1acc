"""A fragment's downloadable files: ``tessera export``'s folder, kept on storage once per content.

:func:`export_folder` runs :func:`common.imports.export.export_fragment` into
``fragments/<id>/downloads/<key>/<id>/`` the first time and returns that folder afterwards. The
key is a content key of the artifacts the files come from (the newest RGBN face of each side and
every render on storage, by path — their names carry their own content keys) and of the export
format, so a new solve or render gives a new folder and an old one is never stale.
:func:`export_zip` adds a zip of the folder beside it (written once, atomically).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from common.store import Store, content_key

#: version of the download layout (part of the key)
DOWNLOADS_VERSION = 1


def export_key(store: Store, fragment: str) -> str:
    """Content key of what ``tessera export`` would write for ``fragment`` now."""
    from common.imports.export import latest_faces

    faces = latest_faces(store, fragment)
    renders = store.path(f"fragments/{fragment}/renders")
    parts = [f"{face}={rel}" for face, rel in faces.items()]
    parts += sorted(p.name for p in renders.glob("*.h5")) if renders.is_dir() else []
    return content_key("downloads", str(DOWNLOADS_VERSION), *parts)


def export_folder(store: Store, fragment: str) -> tuple[Path, str]:
    """``(folder, key)``: the exported files of ``fragment``, exporting them first if needed.

    Raises ValueError (from the export) when the fragment has no RGBN face.
    """
    from common.imports.export import export_fragment

    key = export_key(store, fragment)
    parent = store.path(f"fragments/{fragment}/downloads/{key}")
    folder = parent / fragment
    if not (folder / "metadata.json").is_file():
        folder = export_fragment(store, fragment, parent, overwrite=True)
    return folder, key


def export_zip(folder: Path, fragment: str) -> Path:
    """A zip (stored, not recompressed: PNGs are compressed already) of an export folder, beside it."""
    from common.store import atomic_file  # the project's one atomic write

    path = folder.parent / f"{fragment}.zip"
    if path.is_file():
        return path
    with atomic_file(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            for p in sorted(folder.iterdir()):
                if p.is_file() and not p.name.startswith("."):
                    z.write(p, f"{fragment}/{p.name}")
    return path
