"""The shared import driver: items in, content-keyed artifacts and events out, resumable.

Every ``tessera import <kind>`` describes its work as a list of :class:`ImportItem` (the files
of one fragment face, its id, the options that change the result) and one ``convert`` function
that reads an item's files, checks them at the door and writes the artifacts. :func:`run_import`
does the rest, the same way for every kind:

* **content keys** -- an item's key is the sha256 of its source files, the kind, the kind's
  algorithm version and its options (:func:`item_key`); ``convert`` names its artifacts with it,
  so writing one again is a no-op (:meth:`common.store.Store.write` keeps an existing file);
* **resumable** -- a ledger in the destination (:class:`Ledger`, JSON lines, one fsynced line per
  item imported) lists the keys done; an interrupted run (Ctrl-C, a killed process, a power cut)
  started again skips them and imports the rest; nothing is imported twice, and an item whose
  files changed has a new key and is imported again. Refused items are not recorded: they are
  tried again on the next run (after the operator fixed them);
* **sinks** -- where artifacts and events go is a *sink*: :class:`StoreSink` writes straight into a
  storage root (no events); the bus sink of ``services/cli/imports.py`` writes to shared storage or,
  when it is unreachable, to the bench's spool, and puts each event into the durable outbox the
  scanner service uses (:class:`common.bus.outbox.Outbox`), so nothing is lost while the lab is down;
* **summary** -- :class:`ImportSummary` counts imported / already imported / refused, with each
  refusal's reason naming the file;
* **the same file twice** -- with ``sources=True`` an item any of whose files (its sha256) was already
  imported as another fragment, or for the same fragment at another dpi, is refused naming what it became
  (:class:`common.imports.sources.SourceIndex`, from the ledger and the artifacts' provenance), unless
  ``allow_duplicates`` / ``replace`` say otherwise; an item's ``shared`` files (an RTI rig's light file)
  are left out of the check.

Interface for a kind (see ``services/cli/import_images.py`` for a complete one)::

    from common.imports import ImportItem, ImportRefused, Output

    def convert(item: ImportItem, store: Store) -> list[Output]:
        image = read_image_checked(item.sources[0])          # raises ImportRefused with the reason
        ...
        ref = save_rgbn(store, f"fragments/{item.fragment}/rgbn/{item.face}-{item.key}.h5", rgbn)
        return [Output("rgbn.ready", ref, {"face": item.face})]

    summary = run_import(items, convert, sink, kind="images", version=VERSION, progress=bar)

``convert`` raises :class:`ImportRefused` (or ``ValueError``) for bad input: the item is refused
with that message and the run goes on. An ``OSError`` while writing to shared storage makes the
driver try the sink's next store (the spool). Any other exception is a bug: the item is refused
with the exception's type and message and the run goes on.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Protocol, Sequence

from common.messages import MessageError, new_message
from common.store import ArtifactError, ArtifactRef, Store, content_key, file_sha256

log = logging.getLogger("tessera.imports")


class ImportRefused(ValueError):
    """An input that must not be imported; the message names the file and the reason."""


@dataclass
class ImportItem:
    """One unit of import: the files of one fragment (face), and how to read them.

    Attributes
    ----------
    name : str
        Shown in the progress bar and the summary (usually the main file's name).
    sources : sequence of path
        Every file read; their digests key the item.
    fragment : str
        Fragment id (inventory id) the artifacts belong to.
    face : str
        ``front`` or ``back`` (or what the kind uses).
    options : dict
        JSON-serialisable settings that change the result (dpi, convention, metadata, ...):
        part of the key.
    key : str
        Filled in by :func:`run_import` (:func:`item_key`); name artifacts with it.
    digests : list of str
        Filled in by :func:`run_import`: the sha256 of each source, in order (for provenance).
    shared : sequence of path
        Those of ``sources`` that are no picture of this fragment and may be the same file for many items
        (a dome's light file, a mask): part of the key, left out of the check for files imported before
        (:meth:`own_digests`).
    """

    name: str
    sources: Sequence[str | os.PathLike]
    fragment: str
    face: str = "front"
    options: dict = field(default_factory=dict)
    key: str = ""
    digests: list = field(default_factory=list)
    shared: Sequence[str | os.PathLike] = ()

    def fill_digests(self) -> list:
        """``digests``, read from the files unless they are already (``OSError`` for a file that cannot be read)."""
        if len(self.digests) != len(self.sources):
            self.digests = [file_sha256(p) for p in self.sources]
        return self.digests

    def own_digests(self) -> list[tuple[str, str]]:
        """``(file name, sha256)`` of the sources that are this fragment's own (all but ``shared``), in order;
        after :func:`item_key` (or :meth:`fill_digests`) filled ``digests``."""
        shared = {os.fspath(p) for p in self.shared}
        return [(Path(p).name, d) for p, d in zip(self.sources, self.digests) if os.fspath(p) not in shared]

    def shared_digests(self) -> list[str]:
        """The sha256 of the ``shared`` sources (what :meth:`own_digests` leaves out), for the ledger and provenance."""
        own = {d for _, d in self.own_digests()}
        return sorted({d for d in self.digests if d not in own})

    def source_provenance(self) -> dict:
        """What an artifact's provenance records of the files it was made from, read back by the check of every
        import (:mod:`common.imports.sources`): ``source_sha256`` (every source, in order), ``shared_sha256``
        (when there are shared sources) and ``dpi`` (``options["dpi"]``). After :meth:`fill_digests`."""
        prov = {"source_sha256": list(self.digests)}
        if self.shared:
            prov["shared_sha256"] = self.shared_digests()
        prov["dpi"] = self.options.get("dpi")
        return prov


@dataclass
class Output:
    """One artifact written by ``convert`` and the event that announces it.

    ``fields`` go into the event besides ``fragment`` (the item's) and ``artifact`` (``ref``),
    e.g. ``{"face": "front"}`` for ``rgbn.ready``.
    """

    type: str
    ref: ArtifactRef
    fields: dict = field(default_factory=dict)


@dataclass
class ImportSummary:
    """What a run did: keys imported now, skipped as already imported, refused with reasons."""

    imported: list[str] = field(default_factory=list)      # item names
    skipped: list[str] = field(default_factory=list)       # already in the ledger
    refused: list[tuple[str, str]] = field(default_factory=list)   # (item name, reason)
    events: int = 0
    interrupted: bool = False

    @property
    def exit_status(self) -> int:
        """0 when everything is in, 1 when something was refused, 130 when interrupted."""
        return 130 if self.interrupted else (1 if self.refused else 0)

    def lines(self) -> list[str]:
        """The summary as lines for a terminal."""
        out = [f"imported {len(self.imported)}, already imported {len(self.skipped)}, refused {len(self.refused)}"
               + (f"; {self.events} event(s) queued" if self.events else "")]
        out += [f"  refused {name}: {reason}" for name, reason in self.refused]
        if self.interrupted:
            out.append("interrupted: run the same command again to import the rest")
        return out


class Sink(Protocol):
    """Where a run's artifacts and events go."""

    def stores(self) -> list[Store]:
        """Stores to write into, in order of preference (shared storage first, then a fallback)."""

    def emit(self, event: dict, ref: ArtifactRef, store: Store) -> bool:
        """Announce ``event`` (its artifact ``ref`` was written into ``store``); True if queued."""

    @property
    def ledger_dir(self) -> Path:
        """Directory holding the ledger of this destination."""


class StoreSink:
    """Write into a storage root; no events (``tessera import ... --store DIR``).

    The ledger is ``<root>/imports/ledger.jsonl``. ``tessera reconcile`` (or the station) queues the
    fragments for the later stages.
    """

    def __init__(self, store: Store):
        self.store = store

    def stores(self) -> list[Store]:
        return [self.store]

    def emit(self, event: dict, ref: ArtifactRef, store: Store) -> bool:
        return False

    @property
    def ledger_dir(self) -> Path:
        return self.store.root / "imports"


class Ledger:
    """Keys of the items imported into one destination: an append-only JSON-lines file.

    Each line is written and fsynced after the item's artifacts and events are durable, so a
    key in the ledger means the item is completely in. A line torn by a crash is ignored.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.done: dict[str, dict] = {}
        if self.path.is_file():
            for line in self.path.read_text(errors="replace").splitlines():
                with contextlib.suppress(ValueError, TypeError, KeyError):
                    rec = json.loads(line)
                    self.done[str(rec["key"])] = rec

    def __contains__(self, key: str) -> bool:
        return key in self.done

    def add(self, record: Mapping) -> None:
        """Append one record (must carry ``key``), durably."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        line = json.dumps(dict(record), sort_keys=True, default=str)
        with open(self.path, "a", encoding="utf-8") as fh:
            # a torn line from an earlier crash must not swallow this one
            if fh.tell() > 0:
                with open(self.path, "rb") as rd:
                    rd.seek(-1, os.SEEK_END)
                    if rd.read(1) != b"\n":
                        fh.write("\n")
            fh.write(line + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        self.done[str(record["key"])] = dict(record)


def item_key(item: ImportItem, kind: str, version: str) -> str:
    """Content key of an item: digests of its files, the kind, its version and its options.

    Fills ``item.digests`` (the files' sha256) when it is empty.
    """
    digests = item.fill_digests()
    opts = json.dumps(item.options, sort_keys=True, default=str)
    return content_key(kind, version, item.fragment, item.face, opts, *digests)


def sink_ledger(sink: Sink) -> Ledger:
    """The ledger of ``sink``'s destination: ``<sink.ledger_dir>/ledger.jsonl``."""
    return Ledger(Path(sink.ledger_dir) / "ledger.jsonl")


def load_sources(sink: Sink, ledger: Ledger | None = None):
    """What was imported into ``sink``'s destination before: a :class:`common.imports.sources.SourceIndex` of
    its ledger (default :func:`sink_ledger`) and its stores' artifacts (cached in ``<sink.ledger_dir>/sources.jsonl``)."""
    from common.imports.sources import SourceIndex

    ledger = ledger if ledger is not None else sink_ledger(sink)

    return SourceIndex.load(sink.stores(), list(ledger.done.values()), Path(sink.ledger_dir) / "sources.jsonl")


def source_conflict(item: ImportItem, index, *, allow_duplicates: bool = False, replace: bool = False) -> str | None:
    """Why ``item`` must not be imported because its own files (not its ``shared`` ones) were imported before
    as another fragment or face, or for this face at another ``options["dpi"]``, or None: the check of every
    import (:meth:`common.imports.sources.SourceIndex.conflict` against ``index``, :func:`load_sources`), which
    ``tessera ps --store`` makes too. Reads the files' digests unless :func:`item_key` did."""
    item.fill_digests()
    own = item.own_digests()
    names = [n for n, _ in own] if len(item.sources) > 1 else None   # which file of a scan set or capture
    return index.conflict([d for _, d in own], item.fragment, item.face, item.options.get("dpi"), item.key,
                          names=names, allow_duplicates=allow_duplicates, replace=replace)


def run_import(items: Iterable[ImportItem], convert: Callable[[ImportItem, Store], list[Output]], sink: Sink, *,
               kind: str, version: str, progress=None, ledger: Ledger | None = None, sources: bool = False,
               allow_duplicates: bool = False, replace: bool = False) -> ImportSummary:
    """Import ``items`` through ``convert`` into ``sink``; resumable, never stops on a bad item.

    Parameters
    ----------
    items : iterable of ImportItem
        The work; a list gives the progress bar its total.
    convert : callable ``(item, store) -> list[Output]``
        Reads and checks the item's files, writes its artifacts into ``store`` (content-keyed by
        ``item.key``), returns what it wrote. Raises :class:`ImportRefused` for bad input.
    sink : Sink
        :class:`StoreSink` or the bus sink of ``services/cli/imports.py``.
    kind, version : str
        Name of the kind (``"images"``) and its algorithm version: part of every key.
    progress : ProgressBar, optional
        Updated after every item (``update(done, name)``).
    ledger : Ledger, optional
        Default: ``<sink.ledger_dir>/ledger.jsonl``.
    sources : bool
        Refuse an item any of whose own source files (sha256; not its ``shared`` ones) was already imported
        as another fragment id (or the other face), or for the same fragment and face at another
        ``options["dpi"]``
        (:meth:`common.imports.sources.SourceIndex.conflict`; what was imported is read from the ledger and
        the stores' artifacts, cached in ``<sink.ledger_dir>/sources.jsonl``).
    allow_duplicates, replace : bool
        With ``sources``: import a file already imported as another fragment anyway; let a file imported
        for this fragment and face at another dpi be imported again at this one (the newest face is the one
        every stage and page uses).

    Returns
    -------
    ImportSummary
        ``interrupted`` is set on KeyboardInterrupt (the ledger then holds every item finished).
    """
    items = list(items)
    ledger = ledger if ledger is not None else sink_ledger(sink)
    summary = ImportSummary()
    check = None
    if sources:
        check = (load_sources(sink, ledger), {"allow_duplicates": allow_duplicates, "replace": replace})
    try:
        for i, item in enumerate(items):
            _one(item, convert, sink, kind, version, ledger, summary, check)
            if progress is not None:
                progress.update(i + 1, item.name)
    except KeyboardInterrupt:
        summary.interrupted = True
    finally:
        if progress is not None:
            progress.close()
    return summary


def _one(item, convert, sink, kind, version, ledger, summary, check=None) -> None:
    try:
        item.key = item_key(item, kind, version)
    except OSError as exc:
        summary.refused.append((item.name, f"cannot read {exc.filename or item.name}: {exc.strerror or exc}"))
        return
    if item.key in ledger:
        summary.skipped.append(item.name)
        return
    if check is not None:   # the same file already imported as another fragment, or at another dpi
        index, policy = check
        reason = source_conflict(item, index, **policy)
        if reason:
            summary.refused.append((item.name, reason))
            return
    stores = sink.stores()
    outputs, used = None, None
    for k, store in enumerate(stores):
        try:
            outputs, used = convert(item, store), store
            break
        except OSError as exc:  # first: storage errors (unreachable, full, read-only) are OSErrors
            if k + 1 < len(stores) and not isinstance(exc, FileNotFoundError):
                log.warning("writing %s to %s failed (%s); using %s", item.name, store.root, exc, stores[k + 1].root)
                continue
            summary.refused.append((item.name, f"{type(exc).__name__}: {exc}"))
            return
        except (ValueError, ArtifactError) as exc:  # ImportRefused, the library's ValueErrors, a bad path
            summary.refused.append((item.name, str(exc)))
            return
        except Exception as exc:  # a bug must not stop a folder of hundreds; it is reported
            log.exception("import of %s failed", item.name)
            summary.refused.append((item.name, f"internal error {type(exc).__name__}: {exc}"))
            return
    try:
        announced = [new_message(out.type, artifact=out.ref, **{"fragment": item.fragment, **out.fields})
                     for out in outputs or []]
    except MessageError as exc:  # e.g. an id the message schema refuses: nothing announced, nothing recorded
        summary.refused.append((item.name, f"cannot announce it: {exc}"))
        return
    events = [event["uid"] for event, out in zip(announced, outputs or []) if sink.emit(event, out.ref, used)]
    summary.events += len(events)
    record = {"key": item.key, "kind": kind, "version": version, "name": item.name, "fragment": item.fragment,
              "face": item.face, "sources": [os.fspath(p) for p in item.sources], "digests": list(item.digests),
              "shared": item.shared_digests(),
              "dpi": item.options.get("dpi"), "artifacts": [o.ref.path for o in outputs or []], "events": events,
              "time": _dt.datetime.now(_dt.timezone.utc).isoformat()}
    ledger.add(record)
    if check is not None:   # a second copy later in the same run is found too
        check[0].add_record(record)
    summary.imported.append(item.name)
