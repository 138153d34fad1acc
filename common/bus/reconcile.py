"""Find fragments whose later stages are missing on storage, and the events that would redo them.

Storage layout (``docs/storage.md``): ``fragments/<id>/<stage>/<face>-<key>.h5``. A stage's
output is missing when its input exists but its folder holds no artifact; re-submitting the
input's event is harmless because every stage's output is content-keyed.
"""

from __future__ import annotations

from pathlib import Path

from common.messages import new_message
from common.store import Store

# (input folder, event announcing it, output folders that event should eventually produce)
PIPELINE: list[tuple[str, str, tuple[str, ...]]] = [
    ("scans", "fragment.ready", ("rgbn",)),
    ("rgbn", "rgbn.ready", ("features", "renders")),
]


def _artifacts(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob("*.h5") if not p.name.startswith("."))


def missing_stages(store: Store) -> list[dict]:
    """Events to submit so that every fragment's later stages get computed.

    Returns
    -------
    list of dict
        ``fragment.ready``/``rgbn.ready`` events (with the input's artifact pointer, digest
        checked from the file) for every input whose output folder(s) are empty, oldest first.
    """
    events = []
    root = store.root / "fragments"
    if not root.is_dir():
        return events
    for frag_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        for src, etype, outputs in PIPELINE:
            inputs = _artifacts(frag_dir / src)
            if not inputs or all(_artifacts(frag_dir / o) for o in outputs):
                continue
            for path in inputs:
                rel = path.relative_to(store.root).as_posix()
                face = path.stem.split("-", 1)[0]
                fields = {"fragment": frag_dir.name, "artifact": store.ref(rel), "reconciled": True}
                if etype != "fragment.ready" or face in ("front", "back"):
                    fields["face"] = face
                events.append(new_message(etype, **fields))
    return events
