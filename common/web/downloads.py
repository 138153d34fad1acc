"""A fragment's downloadable files: ``tessera export``'s folder, kept on storage once per content.

:func:`export_folder` runs :func:`common.imports.export.export_fragment` into
``fragments/<id>/downloads/<key>/<id>/`` the first time and returns that folder afterwards. The
key is a content key of the artifacts the files come from (the newest RGBN face of each side and
every render on storage, by path — their names carry their own content keys) and of the export
format, so a new solve or render gives a new folder and an old one is never stale.
:func:`export_zip` adds a zip of the folder beside it (written once, atomically). Both check the
free space of the storage before writing anything (:func:`common.store.check_free_space`: the
files' sizes plus a margin) and raise :class:`~common.store.StorageFull`, naming the bytes needed
and available, when it lacks (the pages answer 507 with that message).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from common.store import Store, check_free_space, content_key

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
    """A zip (stored, not recompressed: PNGs are compressed already) of an export folder, beside it.

    Raises :class:`~common.store.StorageFull` before writing when the storage has not the room
    for it (:func:`zip_size`).
    """
    from common.store import atomic_file  # the project's one atomic write

    path = folder.parent / f"{fragment}.zip"
    if path.is_file():
        return path
    members = [(p, f"{fragment}/{p.name}") for p in sorted(folder.iterdir())
               if p.is_file() and not p.name.startswith(".")]
    check_free_space(path.parent, zip_size([(p.stat().st_size, arc) for p, arc in members]), f"the zip {path}")
    with atomic_file(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as z:
            for p, arc in members:
                z.write(p, arc)
    return path


def zip_size(members: list[tuple[int, str]]) -> int:
    """Upper bound of the bytes of a stored (uncompressed) zip of ``(size, name in the archive)`` members.

    Each member's bytes, its local header (30 bytes + name + a ZIP64 extra field of up to 20 and
    a data descriptor of up to 24) and its central-directory entry (46 + name + up to 28 of ZIP64
    extra), and the end records (22, plus 76 for ZIP64): PKWARE APPNOTE 6.3.10 §4.3.

    Examples
    --------
    >>> import io, zipfile
    >>> buf = io.BytesIO()
    >>> with zipfile.ZipFile(buf, "w") as z:
    ...     z.writestr("F1/a.png", b"x" * 1000)
    >>> len(buf.getvalue()) <= zip_size([(1000, "F1/a.png")])
    True
    """
    return 98 + sum(size + 2 * len(name.encode("utf-8")) + 30 + 20 + 24 + 46 + 28 for size, name in members)
