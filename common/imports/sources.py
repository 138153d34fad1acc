"""What was imported before, by the content of its source files: the same picture, scan or capture is not
imported twice.

An import names its artifacts by a content key that includes the fragment id and the options (dpi, …), so
the same file imported under a second id (once with a manifest's inventory number, once by its file name),
or for the same fragment at another dpi, made a second fragment or a second, rescaled face: the matcher then
proposed the two copies as a join near the top of its queue. :class:`SourceIndex` knows, for each sha256 of
a source file, which fragment face it became and at what dpi, from what is already stored:

* the **ledger** of the destination (:class:`common.imports.driver.Ledger`): every item imported since the
  ledger kept its files' ``digests`` and ``dpi`` (a record whose artifacts are no longer on storage is
  ignored), less its ``shared`` ones;
* the **artifacts on storage** (shared storage and the bench's spool): the provenance of every RGBN face and
  every scan set (``fragments/<id>/scans/``): ``source_sha256`` (one digest or a list) less ``shared_sha256``,
  and ``dpi``, as every ``tessera import`` writes them, for what was imported elsewhere (another bench, an
  older ledger). Artifacts are immutable, so what one says is read once and kept in ``sources.jsonl`` beside
  the ledger; later runs open only new ones.

A *shared* file is one of an item's files that is no picture of the fragment and may be the same file for
many (an RTI rig's light file, its intensities, a mask): it keys the item but says nothing about which
fragment it is. Every other file does: a scan set or a capture any of whose pictures was imported as
another fragment is that fragment again (``docs/import.md``).

:meth:`SourceIndex.conflict` is the check :func:`common.imports.driver.run_import` makes before converting an
item, for every ``tessera import`` kind (``docs/import.md``, "The same files twice" and "Importing the same picture
twice").
"""

from __future__ import annotations

import contextlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from common.store import ArtifactError, Store


@dataclass(frozen=True)
class ImportedSource:
    """One source file's content as imported: the face it became."""

    sha256: str
    fragment: str
    face: str
    dpi: float | None
    key: str         # the item's content key (the artifact is ``fragments/<fragment>/rgbn/<face>-<key>.h5``,
    #                  or ``fragments/<fragment>/scans/scans-<key>.h5`` for a scan set, whose face is front)
    artifact: str    # relative path of the artifact


def _dpi(value) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if v > 0 else None


def _digests(value) -> list[str]:
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value] if isinstance(value, (list, tuple)) else []


def _own(digests, shared) -> list[str]:
    """``digests`` less the ``shared`` ones (see the module docstring)."""
    shared = set(_digests(shared))
    return [d for d in _digests(digests) if d not in shared]


def _record_shared(rec: dict) -> list[str]:
    """The shared digests of a ledger record. Records written before the ledger said (``shared`` missing) are
    taken as the importers made them then: only ``tessera import rti`` had shared files, which are those that
    are no image or are named mask (its light file, intensities and mask; the images are the capture)."""
    if "shared" in rec:
        return _digests(rec["shared"])
    if rec.get("kind") != "rti":
        return []
    from common.imports.manifest import IMAGE_SUFFIXES

    return [d for p, d in zip(rec.get("sources") or [], _digests(rec.get("digests")))
            if Path(str(p)).suffix.lower() not in IMAGE_SUFFIXES or "mask" in Path(str(p)).name.lower()]


class SourceIndex:
    """Imported source files by sha256 (see the module docstring)."""

    def __init__(self, entries: Iterable[ImportedSource] = ()):
        self._by_sha: dict[str, list[ImportedSource]] = {}
        for e in entries:
            self.add(e)

    def add(self, entry: ImportedSource) -> None:
        known = self._by_sha.setdefault(entry.sha256, [])
        if entry not in known:
            known.append(entry)

    def add_record(self, rec: dict) -> bool:
        """Add what a ledger record imported (its ``digests`` less its ``shared``, ``fragment``, ``face``, ``dpi``,
        ``key`` and first artifact); False for a record without them (written before the ledger kept digests)."""
        digests = _own(rec.get("digests"), _record_shared(rec))
        arts = [str(a) for a in rec.get("artifacts") or [] if str(a).endswith(".h5")]
        if not digests or not arts:
            return False
        for sha in digests:
            self.add(ImportedSource(sha, str(rec["fragment"]), str(rec.get("face", "")), _dpi(rec.get("dpi")),
                                    str(rec["key"]), arts[0]))
        return True

    def find(self, sha256: str) -> list[ImportedSource]:
        """The faces a file of this content became (oldest known first)."""
        return list(self._by_sha.get(sha256, []))

    def __len__(self) -> int:
        return sum(len(v) for v in self._by_sha.values())

    @classmethod
    def load(cls, stores: Iterable[Store], ledger_records: Iterable[dict], cache: str | os.PathLike | None = None
             ) -> "SourceIndex":
        """The index of what the ledger records and the stores hold (see the module docstring).

        Parameters
        ----------
        stores : iterable of Store
            Where artifacts are (shared storage, the spool).
        ledger_records : iterable of dict
            The destination's ledger lines (:attr:`Ledger.done` values).
        cache : path, optional
            ``sources.jsonl``: what each artifact's provenance said, read once (appended to).
        """
        stores = list(stores)

        def exists(rel: str) -> bool:
            return any(s.path(rel).is_file() for s in stores)

        index, seen = cls(), set()
        for rec in ledger_records:
            arts = [str(a) for a in rec.get("artifacts") or [] if str(a).endswith(".h5")]
            if arts and exists(arts[0]) and index.add_record(rec):
                seen.update(arts)
        cached: dict[str, dict] = {}
        if cache is not None and Path(cache).is_file():
            for line in Path(cache).read_text(errors="replace").splitlines():
                with contextlib.suppress(ValueError, TypeError, KeyError):
                    rec = json.loads(line)
                    cached[str(rec["artifact"])] = rec
        fresh = []
        for store in stores:
            faces_and_scan_sets = sorted(store.root.glob("fragments/*/rgbn/*.h5")) + \
                sorted(store.root.glob("fragments/*/scans/*.h5"))
            for path in faces_and_scan_sets:
                rel = path.relative_to(store.root).as_posix()
                if rel in seen:
                    continue
                seen.add(rel)
                rec = cached.get(rel)
                if rec is None:
                    rec = _provenance_sources(store, rel)
                    if rec is None:
                        continue   # unreadable now (being written, damaged): looked at again next time
                    fresh.append(rec)
                fragment, name = rel.split("/")[1], path.stem
                face, _, key = name.partition("-")
                face = "front" if rel.split("/")[2] == "scans" else face   # a scan set: both faces, one item (front)
                for sha in _digests(rec.get("digests")):
                    index.add(ImportedSource(sha, fragment, face, _dpi(rec.get("dpi")), key, rel))
        if cache is not None and fresh:
            with contextlib.suppress(OSError):   # a cache: a run that cannot write it reads the artifacts again
                Path(cache).parent.mkdir(parents=True, exist_ok=True)
                with open(cache, "a", encoding="utf-8") as fh:
                    fh.writelines(json.dumps(r, sort_keys=True) + "\n" for r in fresh)
        return index

    def conflict(self, sha256s: Iterable[str], fragment: str, face: str, dpi, key: str, *,
                 allow_duplicates: bool = False, replace: bool = False, names=None) -> str | None:
        """Why an item whose files have these digests must not be imported as ``fragment``'s ``face`` at
        ``dpi`` (content key ``key``), or None. ``names``: the files' names, in the order of ``sha256s``, to
        say which file of several (a scan set, a capture) is the one already imported.

        * any file already imported as another fragment (or the other face of this one): refused unless
          ``allow_duplicates``, naming the fragment, its face and dpi;
        * a file imported for this fragment and face only at other dpi values: refused unless ``replace``,
          naming both dpi values (a second, rescaled copy of the face otherwise);
        * the same fragment, face and a dpi it was imported at, under another key (other metadata or
          options): no conflict, the new face replaces the old as before.
        """
        dpi = _dpi(dpi)

        def same(a, b):
            return abs(a - b) <= 1e-6 * max(a, b)

        sha256s = list(sha256s)
        names = list(names) if names is not None else [None] * len(sha256s)
        for sha, name in zip(sha256s, names):
            found = [e for e in self.find(sha) if e.key != key]
            which = f"{name}: " if name else ""
            for e in found:
                if (e.fragment, e.face) != (fragment, face) and not allow_duplicates:
                    at = f", {e.dpi:g} dpi" if e.dpi else ""
                    return (f"{which}the same file (sha256 {sha[:12]}…) is already imported as fragment "
                            f"{e.fragment} ({e.face}{at}: {e.artifact}); not imported again as {fragment} ({face}): "
                            "give --allow-duplicates to import it anyway")
            here = [e.dpi for e in found if (e.fragment, e.face) == (fragment, face) and e.dpi]
            # at a dpi this face already has (from this file) it is no rescaled copy: other metadata, as before
            if dpi and here and not any(same(dpi, d) for d in here) and not replace:
                return (f"{which}the same file is already imported for fragment {fragment} ({face}) at "
                        f"{here[-1]:g} dpi; this import gives {dpi:g} dpi: give --replace to make the {dpi:g} dpi "
                        f"face replace the {here[-1]:g} dpi one")
        return None


def _provenance_sources(store: Store, rel: str) -> dict | None:
    """``{"artifact", "digests", "dpi"}`` from an RGBN or scans artifact's provenance (digests: ``source_sha256``
    less ``shared_sha256``; none: not an import of files), or None when it cannot be read. The dpi is the
    provenance's, else the face's (a scan set's: its first scan's)."""
    try:
        with store.open(rel) as f:
            dpi = f.attrs.get("dpi")
            if dpi is None and "front/scan_0" in f:
                dpi = f["front/scan_0"].attrs.get("dpi")
            try:
                prov = store.provenance(f)
            except ValueError:
                prov = {}
    except (ArtifactError, OSError):
        return None
    prov = prov if isinstance(prov, dict) else {}
    return {"artifact": rel, "digests": _own(prov.get("source_sha256"), prov.get("shared_sha256")),
            "dpi": _dpi(prov.get("dpi", dpi))}
