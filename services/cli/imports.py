"""``tessera import KIND ...``: files a lab already has -> the artifacts and events a capture makes.

    tessera import images PHOTOS... [--manifest CSV] [--dpi D] [--store DIR | --config station.toml]
    tessera import normals NORMAL_MAPS... [--albedo ...] [--convention opengl|directx] [--store DIR]
    tessera import scans ...        (when present)
    tessera import rti DIR...       (when present)

Each kind is a module ``services/cli/import_<kind>.py`` listed in :data:`KINDS` (a kind whose
module is not there yet is skipped, as ``services/cli/__init__.py`` does for commands). A kind
module exposes ``add_parser(subparsers)``; its parser calls :func:`add_sink_arguments` and its
``func`` ends with :func:`run_items`::

    def add_parser(subparsers):
        p = subparsers.add_parser("images", help="...")
        p.add_argument("paths", nargs="+")
        add_sink_arguments(p)
        p.set_defaults(func=run)

    def run(args):
        items = [ImportItem(name=..., sources=[path], fragment=..., face="front", options={...})]
        return run_items(args, items, convert, kind="images", version=VERSION)

Sinks (:func:`open_sink`): ``--store DIR`` writes straight into a storage root (no events;
``tessera reconcile`` queues the fragments later). Without ``--store`` the artifacts go to the
config's shared storage -- or, when it is unreachable, to the bench's spool ``[scanner] spool_dir``
-- and every event into the same durable outbox as the scanner service
(:class:`common.bus.outbox.Outbox`), drained in the background by the scanner's
:class:`services.scanner.Drainer`. At the end the command waits up to ``--wait`` seconds for the
outbox to drain; what is left stays in the outbox and goes out when ``tessera station`` runs on this
machine (it drains the outbox while it runs), or with the next ``tessera import`` or ``tessera scanner`` here. Resumability, content keys and the summary are
:func:`common.imports.run_import`'s.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Mapping

from common.imports import ImportItem, Output, ProgressBar, StoreSink, run_import
from common.store import ArtifactRef, Store

log = logging.getLogger("tessera.import")

# kind modules in services/cli/, in the order shown by --help
KINDS = ["import_scans", "import_rti", "import_images", "import_normals"]


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("import", help="bring files a lab already has into the station (checked at the door)",
                              description=__doc__.split("\n\n")[0],
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    kinds = p.add_subparsers(dest="kind", metavar="KIND")
    for name in KINDS:
        try:
            module = importlib.import_module(f"services.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"services.cli.{name}":
                continue  # kind not part of this build (yet)
            raise
        module.add_parser(kinds)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def add_sink_arguments(p: argparse.ArgumentParser) -> None:
    """``--store DIR``, ``--wait S``, ``--config``/``--set``, and ``--allow-duplicates`` / ``--replace`` (what the
    check of every import against the files imported before lets through, :func:`run_items`): the options every
    kind shares."""
    g = p.add_argument_group("destination")
    g.add_argument("--store", metavar="DIR",
                   help="write into this storage root, no events "
                        "(default: the station's storage, events via the outbox)")
    g.add_argument("--wait", type=float, default=30.0, metavar="S",
                   help="seconds to wait for the outbox to drain at the end "
                        "(default 30; the rest waits for the next run)")
    add_duplicate_arguments(p)
    from common.config import add_config_arguments
    add_config_arguments(p)


def add_duplicate_arguments(p: argparse.ArgumentParser) -> None:
    """``--allow-duplicates`` / ``--replace``: what the check against the files imported before lets through
    (:func:`common.imports.source_conflict`), for every import and for ``tessera ps --store``."""
    g = p.add_argument_group("the same file imported before")
    g.add_argument("--allow-duplicates", action="store_true",
                   help="import a file whose content is already imported as another fragment (refused by default)")
    g.add_argument("--replace", action="store_true",
                   help="import a file already imported for the same fragment and face at another dpi, the new face "
                        "replacing the old (refused by default)")


class BusSink:
    """Shared storage (or the bench's spool when it is unreachable) + the scanner's durable outbox."""

    def __init__(self, config: Mapping):
        from common.bus.outbox import Outbox
        from services.scanner import Drainer
        self.storage = Store.from_config(config)
        self.outbox = Outbox(config["scanner"]["spool_dir"])
        # an event whose artifact is already queued (a run killed before its ledger line) is not queued twice
        self._queued = {e.get("artifact", {}).get("path") for _, e, _ in self.outbox.pending()}
        self.drainer = Drainer(config, self.outbox, self.storage)
        self.drainer.start()

    @property
    def ledger_dir(self) -> Path:
        return self.outbox.dir / "imports"

    def stores(self) -> list[Store]:
        return ([self.storage] if self.storage.available() else []) + [self.outbox.spool]

    def emit(self, event: dict, ref: ArtifactRef, store: Store) -> bool:
        if ref.path in self._queued:
            return False
        spooled = store is self.outbox.spool
        self.outbox.put(event, spooled=ref.path if spooled else None, sha256=ref.sha256 if spooled else None)
        self._queued.add(ref.path)
        self.drainer.wake.set()
        return True

    def close(self, wait_s: float, out=None) -> int:
        """Wait up to ``wait_s`` for the outbox to drain; return how many events stay in it."""
        deadline = time.monotonic() + max(0.0, wait_s)
        while len(self.outbox) and time.monotonic() < deadline:
            self.drainer.wake.set()
            threading.Event().wait(0.2)
        self.drainer.stop.set()
        self.drainer.wake.set()
        self.drainer.join(5)
        left = len(self.outbox)
        self.outbox.close()
        if left:
            print(f"{left} event(s) wait in the outbox {self.outbox.dir} (lab unreachable); they go out when "
                  f"`tessera station` runs on this machine, or with the next `tessera import` or `tessera scanner`", file=out or sys.stderr)
        return left


def open_sink(args):
    """The sink named by the arguments: :class:`StoreSink` for ``--store``, else :class:`BusSink`."""
    if getattr(args, "store", None):
        return StoreSink(Store(args.store))
    from common.config import config_from_arguments
    return BusSink(config_from_arguments(args))


def run_items(args, items: list[ImportItem], convert: Callable[[ImportItem, Store], list[Output]], *,
              kind: str, version: str, out=None) -> int:
    """Run the shared driver over ``items`` into the sink of ``args``; print the summary; exit status.

    0 = everything imported (or already), 1 = something refused, 130 = interrupted. A file already imported
    as another fragment or at another dpi is refused (:func:`run_import` with ``sources``), unless
    ``--allow-duplicates`` / ``--replace`` (:func:`add_sink_arguments`) let it through.
    """
    if not items:
        print(f"tessera import {kind}: nothing to import", file=sys.stderr)
        return 2
    try:
        sink = open_sink(args)
    except (OSError, ValueError) as exc:  # an unusable --store, a bad --config (ConfigError)
        where = f"--store {args.store}" if getattr(args, "store", None) else "the station's storage and outbox"
        print(f"tessera import {kind}: cannot use {where}: {exc}", file=sys.stderr)
        return 2
    bar = ProgressBar(len(items), f"import {kind}")
    try:
        summary = run_import(items, convert, sink, kind=kind, version=version, progress=bar, sources=True,
                             allow_duplicates=bool(getattr(args, "allow_duplicates", False)),
                             replace=bool(getattr(args, "replace", False)))
    finally:
        if isinstance(sink, BusSink):
            sink.close(args.wait)
    out = out if out is not None else sys.stdout   # looked up now: the caller may have redirected it
    lines = summary.lines()
    print(f"tessera import {kind} into {args.store or 'the station'}: {lines[0]}", file=out)
    for line in lines[1:]:
        print(line, file=sys.stderr)
    return summary.exit_status
