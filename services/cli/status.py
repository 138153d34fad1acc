"""tessera status — queues, workers per host, jobs in flight, parked failures, throughput."""

from __future__ import annotations

from common.config import add_config_arguments, config_from_arguments
from common.messages import to_json


def add_parser(sub) -> None:
    p = sub.add_parser("status", help="broker status: queues, workers, in flight, parked failures")
    p.add_argument("--json", action="store_true", help="print the raw status as JSON")
    p.add_argument("--rerun", metavar="JOB", help="re-queue a parked job (or 'all')")
    add_config_arguments(p)
    p.set_defaults(func=run)


def format_status(s: dict) -> str:
    lines = [f"broker {s['host']} pid {s['pid']}  up {s['uptime_s']:.0f} s  stream {s['stream']} seq {s['last_seq']}  "
             f"completed {s['completed']}  {s['jobs_per_s']:.1f} jobs/s  journal {s['journal_bytes'] / 1e6:.1f} MB"]
    lines.append("queues:   " + ("  ".join(f"{k}={v}" for k, v in s["queues"].items()) or "-"))
    lines.append("workers:")
    for host, ws in s["workers"].items():
        lines.append(f"  {host}: " + ", ".join(f"{w['service']}[{w['pid']}]{'*' if w['job'] else ''}" for w in ws))
    if not s["workers"]:
        lines.append("  (none)")
    lines.append(f"in flight: {len(s['in_flight'])}")
    for j in s["in_flight"]:
        prog = f" {j['progress'][0]:.0%} {j['progress'][1]}" if j.get("progress") else ""
        lines.append(f"  {j['job']:<24} {j['service']:<10} {j['fragment'] or '':<10} {j['worker']} "
                     f"{j['running_s']:.1f} s attempt {j['attempt']}{prog}")
    if not s.get("journal_ok", True):
        lines.append("JOURNAL CANNOT WRITE (disk full?): submissions are refused; see the broker log")
    refused = s.get("refused") or {}
    if refused:
        lines.append("refused frames: " + "  ".join(f"{k}={v}" for k, v in sorted(refused.items())))
    lines.append(f"parked: {len(s['parked'])}")
    for j in s["parked"]:
        lines.append(f"  {j['job']:<24} {j['service']:<10} {j['fragment'] or '':<10} after {j['attempts']}: {j['error']}")
    return "\n".join(lines)


def run(args) -> int:
    from common.bus.client import BrokerClient, BrokerUnavailable
    config = config_from_arguments(args)
    try:
        with BrokerClient.from_config(config) as bus:
            if args.rerun:
                jobs = bus.rerun(args.rerun)
                print(f"re-queued {len(jobs)} job(s): {' '.join(jobs)}")
                return 0 if jobs else 1
            s = bus.status()
    except BrokerUnavailable as exc:
        print(f"error: {exc}")
        return 1
    try:
        print(to_json(s, indent=2) if args.json else format_status(s), flush=True)
    except BrokenPipeError:  # `tessera status | head`: the reader left; that is not an error
        import os
        import sys
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second complaint at exit
    return 0
