"""The scanner process at the bench: capture fragments, store their scans, emit ``fragment.ready``.

parse config -> open the scanner (simulated flatbed with the synthetic fresco by default, or a
SANE device) -> for each fragment: guide the operator through the capture workflow
(:func:`common.acquisition.capture.capture_fragment`), write the scans to shared storage or, when
it is unreachable, to the local spool -> put ``fragment.ready`` in the durable outbox. A
background thread drains the outbox in order whenever the broker and the storage answer, so the
bench never waits for the lab.
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Callable, Iterator, Mapping

from common.bus.client import BrokerClient
from common.bus.outbox import Outbox
from common.messages import FRAGMENT_PATTERN, new_message
from common.store import Store

SERVICE = "scanner"
log = logging.getLogger("tessera.scanner")


def fragments(config: Mapping, count: int) -> Iterator[tuple[str, object]]:
    """(fragment id, physical surface) of ``count`` synthetic fresco fragments (simulated device)."""
    from common.synth import generate_wall
    sc = config["scanner"]
    # a wall of at least 8 pieces: tiny walls are atypical (and the painter needs some room)
    wall = generate_wall(max(int(count), 8), int(sc["seed"]), dpi=float(sc["wall_dpi"]))
    for frag in wall.fragments[:count]:
        yield frag.id, frag.surface


def ask(prompt: str, out=sys.stdout) -> str:
    """One line the operator types, the prompt shown on ``out`` with the station's other messages (``input()``
    always prompts on stdout). EOFError when the terminal's input is closed."""
    print(prompt, end="", file=out, flush=True)
    line = sys.stdin.readline()
    if not line:
        raise EOFError("the operator's input is closed")
    return line.rstrip("\r\n")


def terminal_operator(scanner, simulated: bool, out=sys.stdout) -> Callable:
    """Show each step in the terminal; on the simulated flatbed do it, on a real one wait for Enter."""
    from common.acquisition.capture import simulated_operator
    act = simulated_operator(scanner) if simulated else None

    def operator(step) -> None:
        print(f"  [{step.index}/{step.total}] {step.instruction}", file=out, flush=True)
        if act is not None:
            act(step)
        else:
            ask("      press Enter when done ", out)
    return operator


def store_scans(result, storage: Store, outbox: Outbox) -> tuple[dict, bool]:
    """Write the scans to storage (or the spool if storage is unreachable) and queue ``fragment.ready``.

    Returns the event and whether the scans went to the spool.
    """
    from common.acquisition.capture import write_scans
    spooled = False
    ref = None
    if storage.available():
        try:
            ref = write_scans(storage, result.fragment_id, result)
        except OSError as exc:  # the share went away mid-write
            log.warning("storage write failed (%s); spooling locally", exc)
    if ref is None:
        ref = write_scans(outbox.spool, result.fragment_id, result)
        spooled = True
    event = new_message("fragment.ready", fragment=result.fragment_id, artifact=ref, device=result.device,
                        colour_only=bool(result.colour_only))
    outbox.put(event, spooled=ref.path if spooled else None, sha256=ref.sha256 if spooled else None)
    return event, spooled


class Drainer(threading.Thread):
    """Drains the outbox every ``drain_interval_s`` (and when woken) until stopped."""

    def __init__(self, config: Mapping, outbox: Outbox, storage: Store):
        super().__init__(name="outbox-drain", daemon=True)
        self.config, self.outbox, self.storage = config, outbox, storage
        self.stop = threading.Event()
        self.wake = threading.Event()

    def run(self) -> None:
        client = BrokerClient.from_config(self.config, timeout_s=min(1.0, self.config["client"]["timeout_s"]), retries=1)
        interval = float(self.config["scanner"]["drain_interval_s"])
        try:
            while not self.stop.is_set():
                try:
                    n = self.outbox.drain(client, self.storage)
                    waiting = len(self.outbox) if n else 0
                    # one event sent as it was made is routine (an import of hundreds would print a line per
                    # picture); a backlog caught up after the broker was away, or one still waiting, is news
                    if n > 1 or waiting:
                        log.info("outbox: %d event(s) delivered, %d waiting", n, waiting)
                    elif n:
                        log.debug("outbox: 1 event delivered")
                except Exception:  # a drain problem must never stop capture
                    log.exception("outbox drain failed; will retry")
                self.wake.wait(interval)
                self.wake.clear()
        finally:
            client.close()


def main(config: Mapping, *, count: int | None = None, wait_drained: bool = True, out=sys.stdout) -> int:
    """Capture ``count`` fragments (default ``[scanner] fragments``), then wait until the outbox is empty."""
    from common.acquisition.capture import CaptureError, capture_fragment
    sc = config["scanner"]
    count = int(sc["fragments"] if count is None else count)
    storage = Store.from_config(config)
    outbox = Outbox(sc["spool_dir"])
    if len(outbox):
        print(f"outbox holds {len(outbox)} event(s) from before; delivering them first", file=out, flush=True)
    drainer = Drainer(config, outbox, storage)
    drainer.start()
    simulated = sc["device"] == "simulated"
    if simulated:
        from common.acquisition.flatbed_sim import SimulatedFlatbed
        scanner = SimulatedFlatbed("sim", seed=int(sc["seed"]))
        source = fragments(config, count)
    else:
        from common.acquisition.scanners import SaneScanner
        scanner = SaneScanner(sc["sane_device"])
        source = ((ask("fragment id: ", out).strip(), None) for _ in range(count))
    operator = terminal_operator(scanner, simulated, out)
    status = 0
    try:
        for i, (fid, surface) in enumerate(source):
            if not FRAGMENT_PATTERN.match(fid):  # the bus refuses other ids (docs/messages.md): ask before scanning
                print(f"  ! fragment id {fid!r} is not valid: use 1-64 letters, digits, '.', '_' or '-'; skipped",
                      file=out, flush=True)
                status = 1
                continue
            print(f"fragment {fid} ({i + 1} of {count})", file=out, flush=True)
            result = None
            for attempt in range(3):  # the operator fixes what the capture complained about, then retries
                if surface is not None:
                    scanner.place(surface)
                try:
                    result = capture_fragment(
                        scanner, fid, operator=operator, dpi=sc["dpi"], prescan_dpi=sc["prescan_dpi"], depth=sc["depth"],
                        colour_only=sc["colour_only"], margin_mm=sc["margin_mm"],
                        progress=lambda f, text: print(f"      {f:4.0%} {text}", file=out, flush=True))
                    break
                except CaptureError as exc:
                    print(f"  ! {getattr(exc, 'operator_message', str(exc))}", file=out, flush=True)
                    if not simulated and ask("      press Enter to retry, or type s to skip: ", out).strip().lower() == "s":
                        break
            if result is None:
                print(f"  fragment {fid} skipped", file=out, flush=True)
                status = 1
                continue
            event, spooled = store_scans(result, storage, outbox)
            where = "local spool (storage unreachable)" if spooled else "storage"
            print(f"  scans of {fid} saved to {where}; fragment.ready queued ({len(outbox)} in outbox)",
                  file=out, flush=True)
            drainer.wake.set()
        while wait_drained and len(outbox):
            print(f"waiting for the lab: {len(outbox)} event(s) in the outbox", file=out, flush=True)
            drainer.wake.set()
            threading.Event().wait(max(1.0, float(sc["drain_interval_s"])))
    except (KeyboardInterrupt, EOFError) as exc:
        print(f"stopped{' (input closed)' if isinstance(exc, EOFError) else ''}; {len(outbox)} event(s) stay in the "
              "outbox for the next start", file=out, flush=True)
        status = 130
    finally:
        drainer.stop.set()
        drainer.wake.set()
        drainer.join(5)
        outbox.close()
    return status
