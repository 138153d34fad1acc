"""Find what is missing on storage, stage by stage and face by face, and the events that redo it.

Storage layout (``docs/storage.md``): ``fragments/<id>/<stage>/<face>-<key>.h5``. Checked per
fragment:

* **solver** — every face the scans artifact holds scans of (groups ``front``/``back`` with at
  least one scan) has an RGBN artifact, and the face's newest one, where the solver made it, was made by
  the solver's current version when ``versions`` gives it; else the scans' ``fragment.ready`` is
  re-submitted (an unreadable scans file counts as "some face expected": its ``rgbn`` folder must not be
  empty). An RGBN an importer made (no scans to solve) is never re-solved;
* **features, renderer** — every RGBN face's newest RGBN artifact has a feature table and an illustration
  made from it (their provenance names it as an input; one that names no input counts) by the stage's current
  version when ``versions`` gives it (``tessera reconcile`` does); else that face's ``rgbn.ready``;
* **matcher** — every front face's feature table is recorded in the matcher's proposal store
  (``fragments`` table: fragment, face, sha256); else its ``features.ready``.

Nothing is re-submitted for a fragment that already has a job queued or in flight at the same or
an earlier stage (the broker's PENDING list): that job will produce the output, and a second one
would only duplicate work. Re-submitting is otherwise harmless: outputs are content-keyed and the
broker announces an output only once.
"""

from __future__ import annotations

import contextlib
import sqlite3
from pathlib import Path
from typing import Iterable, Mapping

from common.messages import new_message
from common.store import Store

FACES = ("front", "back")
# event type -> its stage's place in the pipeline (a pending job at a place <= this covers it)
LEVEL = {"fragment.ready": 0, "rgbn.ready": 1, "features.ready": 2}


def _artifacts(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.glob("*.h5") if not p.name.startswith(".")), key=lambda p: (p.stat().st_mtime, p.name))


def _face(path: Path) -> str:
    return path.stem.split("-", 1)[0]


def _provenance(store: Store, artifact: Path) -> dict | None:
    """An artifact's provenance; None when it cannot be read (it then stands for nothing)."""
    try:
        with store.open(artifact.relative_to(store.root).as_posix()) as f:
            return store.provenance(f)
    except Exception:  # noqa: BLE001 - unreadable, whatever the reason
        return None


def _by_another_version(prov: dict, version: str | None) -> bool:
    """Whether provenance names a ``stage_version`` other than ``version`` (None: any version counts; one that
    records none counts as made by it)."""
    return version is not None and prov.get("stage_version") not in (None, version)


def _made_by_older_solver(store: Store, rgbn: Path, version: str | None) -> bool:
    """Whether an RGBN artifact was made by the solver stage at a version other than ``version`` (None: no
    version is current, so none is older). Imported RGBN (another ``stage``), RGBN that records no version
    and unreadable files are not: they are not the solver's to redo."""
    prov = _provenance(store, rgbn) if version is not None else None
    return prov is not None and prov.get("stage") == "solver" and _by_another_version(prov, version)


def _made_from(store: Store, output: Path, source_rel: str, version: str | None = None) -> bool:
    """Whether an output artifact was made from ``source_rel``: its provenance ``inputs`` name it, or name
    nothing (an artifact that records no inputs counts, as before provenance was read). An output of an
    older RGBN of the face does not count: the newest one still needs its own. With ``version`` (the stage's
    current ``VERSION``), an output whose provenance names another ``stage_version`` does not count either:
    it was made by an older stage (one that records none counts). An unreadable output does not count."""
    prov = _provenance(store, output)
    if prov is None or _by_another_version(prov, version):
        return False
    inputs = prov.get("inputs") or []
    return not inputs or any(isinstance(i, dict) and i.get("path") == source_rel for i in inputs)


def _faces_scanned(store: Store, rel: str) -> set[str] | None:
    """Faces a scans artifact holds scans of; None if it cannot be read as one."""
    try:
        with store.open(rel) as f:
            faces = {face for face in FACES if face in f and len(f[face]) > 0}
    except Exception:  # noqa: BLE001 - any unreadable file: fall back to "some output expected"
        return None
    return faces or None


def matched_faces(db_path: str | Path | None) -> set[tuple[str, str, str]] | None:
    """(fragment, face, sha256) the matcher's proposal store has recorded; None without a store."""
    if db_path is None or not Path(db_path).is_file():
        return None
    with contextlib.closing(sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10)) as con:
        try:
            return {(str(a), str(b), str(c)) for a, b, c in con.execute("SELECT fragment, face, sha256 FROM fragments")}
        except sqlite3.Error:
            return None


def missing_stages(store: Store, *, pending: Iterable[tuple] | None = None,
                   matcher_db: str | Path | None = None, versions: Mapping[str, str] | None = None) -> list[dict]:
    """Events to submit so that every fragment's later stages get computed.

    Parameters
    ----------
    store : Store
        The storage to inspect.
    pending : iterable of (service, state, type, fragment, face), optional
        The broker's queued and in-flight jobs (:meth:`BrokerClient.pending`); an event is not
        proposed for a fragment face that has a job pending at the same or an earlier stage.
    matcher_db : path, optional
        The matcher's proposal store; without it the matcher step is not checked.
    versions : mapping, optional
        Folder (``"rgbn"``, ``"features"``, ``"renders"``) → the ``VERSION`` its stage writes now: an output made
        by another version of the stage is missing too (a face drawn before a fix of the renderer is drawn again;
        a face solved before a fix of the solver is solved again from its scans). Without it any version counts.

    Returns
    -------
    list of dict
        ``fragment.ready`` / ``rgbn.ready`` / ``features.ready`` events with the input's artifact
        pointer (digest computed from the file), fragment by fragment, earlier stages first.
        Each carries ``reconciled: true`` and ``missing``: the stages (folders) it is for.
    """
    busy: dict[tuple[str, str | None], int] = {}
    for _service, _state, etype, fragment, face in pending or ():
        level = LEVEL.get(etype)
        if level is not None and fragment is not None:
            key = (str(fragment), face)
            busy[key] = min(busy.get(key, 99), level)
    matched = matched_faces(matcher_db)

    def covered(fragment: str, face: str | None, level: int) -> bool:
        return min(busy.get((fragment, face), 99), busy.get((fragment, None), 99)) <= level

    events = []
    root = store.root / "fragments"
    if not root.is_dir():
        return events
    for frag_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        frag = frag_dir.name
        rgbn = _artifacts(frag_dir / "rgbn")
        newest_rgbn = {_face(p): p for p in rgbn}  # sorted oldest first: the last one wins
        # a face whose newest RGBN an older solver made is as good as unsolved (its re-solve is the newest then)
        rgbn_faces = {face for face, p in newest_rgbn.items()
                      if not _made_by_older_solver(store, p, (versions or {}).get("rgbn"))}
        solving = set()    # faces the solver makes (again): their later stages follow from the new RGBN
        for scans in _artifacts(frag_dir / "scans")[-1:]:  # the newest capture of the fragment
            rel = scans.relative_to(store.root).as_posix()
            expected = _faces_scanned(store, rel)
            missing = sorted(expected - rgbn_faces) if expected is not None else ([] if rgbn_faces else ["?"])
            solving = set(FACES) if missing == ["?"] else set(missing)
            if missing and not covered(frag, None, 0):
                events.append(new_message("fragment.ready", fragment=frag, artifact=store.ref(rel), reconciled=True,
                                          missing=[f"rgbn/{m}" for m in missing]))
        for face, path in sorted(newest_rgbn.items()):
            if face in solving:
                continue
            rel = path.relative_to(store.root).as_posix()
            missing = [d for d in ("features", "renders")
                       if not any(_face(p) == face and _made_from(store, p, rel, (versions or {}).get(d))
                                  for p in _artifacts(frag_dir / d))]
            if missing and not covered(frag, face, 1):
                events.append(new_message("rgbn.ready", fragment=frag, face=face, artifact=store.ref(rel),
                                          reconciled=True, missing=[f"{d}/{face}" for d in missing]))
        if matched is not None:
            feats = {_face(p): p for p in _artifacts(frag_dir / "features")}
            path = feats.get("front")
            if path is not None and not covered(frag, "front", 2):
                ref = store.ref(path.relative_to(store.root).as_posix())
                if (frag, "front", ref.sha256) not in matched:
                    events.append(new_message("features.ready", fragment=frag, face="front", artifact=ref,
                                              reconciled=True, missing=["matcher/front"]))
    return events
