"""No-op stage: the plumbing's test subject and the broker benchmark's worker.

Takes any event. If the event points at an artifact it opens it through the store (so size,
sha256 and HDF5 readability are checked exactly as a real stage would), optionally sleeps
(``[services.noop] sleep_s``, reporting progress), optionally writes a content-keyed output
artifact (``write_output``), and returns one ``noop.done`` event naming the job and the time the
worker received it (``emit = false`` returns nothing). A ``noop.job`` event with ``fail = true``
raises (``"exit"``: SystemExit; ``"bad-event"``: returns a malformed event), to exercise retries
and parking.
"""

from __future__ import annotations

import time

from common.messages import new_message
from common.store import content_key

SERVICE = "noop"
VERSION = "1"


def handle(job: dict, ctx) -> list[dict]:
    received = time.time()
    cfg = ctx.config
    source = job.get("artifact")
    if source:  # with [services.noop] schema/schema_version set it checks them like a real stage
        schema, version = cfg.get("schema"), cfg.get("schema_version")
        with ctx.store.open(source, schema=schema, version=version):
            pass
    sleep_s = float(cfg.get("sleep_s", 0.0))
    steps = max(1, int(sleep_s / 0.05))
    for i in range(steps if sleep_s > 0 else 0):
        time.sleep(sleep_s / steps)
        ctx.progress((i + 1) / steps, "sleeping")
    fail = job.get("fail")
    if fail == "exit":         # a stage that calls sys.exit must not stop the worker
        raise SystemExit(3)
    if fail == "bad-event":    # a stage returning a malformed event is a stage failure
        return [{"type": "noop.done"}]
    if fail:
        raise RuntimeError(f"noop job {job['uid']} asked to fail")
    out = {}
    if cfg.get("write_output", False):
        key = content_key(source["sha256"] if source else job["uid"], SERVICE, VERSION)
        frag = job.get("fragment")
        rel = f"fragments/{frag}/noop/{job.get('face', 'both')}-{key}.h5" if frag else f"noop/{key}.h5"
        ref = ctx.store.write(rel, "tessera.noop", 1, lambda f: f.create_dataset("received", data=received),
                              provenance={"input": job["uid"], "service": SERVICE, "version": VERSION})
        out["artifact"] = ref
    if not cfg.get("emit", True):
        return []
    extra = {k: job[k] for k in ("fragment", "face") if k in job}
    return [new_message("noop.done", job=job["uid"], received=received, attempt=ctx.attempt, **extra, **out)]
