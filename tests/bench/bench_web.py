"""Benchmark of the web pages' server side: what a page waits for.

    python tests/bench/bench_web.py [--fragments 500] [--proposals 10000] [--dpi 300]

Prints, each the median of several requests through Flask's test client (no network):
* ``/api/bench`` with N fragments scanned today (the bench page's live poll: storage tree walk);
* ``/api/review/queue`` with M proposals in the matcher's SQLite store;
* the four review pictures of one proposal between two fragments of a synthetic fresco at the
  given dpi (first request: render; second: cache).
Targets: live poll and queue well under 0.5 s; a proposal's pictures under 2 s (first view).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from common.matching.proposals import Proposal, ProposalStore  # noqa: E402
from common.rgbn.image import save_rgbn  # noqa: E402
from common.store import Store  # noqa: E402
from common.web.compose import relative_pose  # noqa: E402
from common.web.review import ReviewData  # noqa: E402
from services import web  # noqa: E402

TOKEN = "bench-token-0123456789abcdef"


def timed(fn, n=5):
    out = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fragments", type=int, default=500)
    ap.add_argument("--older", type=int, default=5000, help="fragments scanned on earlier days")
    ap.add_argument("--proposals", type=int, default=10000)
    ap.add_argument("--dpi", type=float, default=300)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="tessera-bench-web-"))
    store = Store(root)

    # today's fragments: scans + some later stages each
    for i in range(args.fragments):
        fid = f"F{i:05d}"
        for stage in ("scans", "rgbn", "features")[: 1 + i % 3]:
            store.write(f"fragments/{fid}/{stage}/front-{i:x}.h5", "tessera.bench", 1,
                        lambda f: f.create_dataset("x", data=np.zeros(1)))

    # fragments of earlier days: the live poll must not pay for them
    import os
    past = time.time() - 3 * 86400
    for i in range(args.older):
        d = root / "fragments" / f"OLD{i:05d}" / "scans"
        d.mkdir(parents=True)
        (d / "scans-0.h5").write_bytes(b"")
        os.utime(d / "scans-0.h5", (past, past))
        os.utime(d, (past, past))

    # proposals in the matcher's store
    db_path = root / "matches" / "proposals.sqlite"
    rng = np.random.default_rng(0)
    with ProposalStore(db_path) as db:
        props = []
        for k in range(args.proposals):
            a, b = sorted(rng.choice(args.fragments, 2, replace=False))
            props.append(Proposal(f"F{a:05d}", f"F{b:05d}", float(rng.random()), "bench"))
        unique = {(p.fragment_a, p.fragment_b): p for p in props}
        db.upsert(list(unique.values()))

    # two real fragments for the pictures
    from common.synth import generate_wall
    t = time.perf_counter()
    wall = generate_wall(4, 3, dpi=args.dpi)
    print(f"(synthetic wall of 4 fragments at {args.dpi:g} dpi: {time.perf_counter() - t:.1f} s)")
    a, b, _ = max(wall.adjacency, key=lambda x: x[2])
    fa = {f.id: f for f in wall.fragments}
    for fid in (a, b):
        save_rgbn(store, f"fragments/{fid}/rgbn/front-wall.h5", fa[fid].rgbn)
    (a, b) = sorted((a, b))
    angle, tx, ty = relative_pose(fa[a].pose, fa[b].pose)
    with ProposalStore(db_path) as db:
        pid = db.upsert([Proposal(a, b, 0.99, "bench", angle_deg=angle, tx_mm=tx, ty_mm=ty)])[0].id

    review = ReviewData(db_path, store)
    app = web.create_app(token=TOKEN, store_root=root, review=review)
    c = app.test_client()
    assert c.get("/api/bench").status_code == 200
    print(f"/api/bench, {args.fragments} fragments today + {args.older} older: "
          f"{1000 * timed(lambda: c.get('/api/bench')):8.1f} ms")
    print(f"/api/review/queue (50 of {len(unique)} proposals):  "
          f"{1000 * timed(lambda: c.get('/api/review/queue')):8.1f} ms")
    print(f"/api/review/fragment/F00001:                {1000 * timed(lambda: c.get('/api/review/fragment/F00001')):8.1f} ms")
    shapes = [fa[x].rgbn.albedo.shape[:2] for x in (a, b)]
    first = {}
    for view in ("pair-colour", "pair-relief", "joined-colour", "joined-relief"):
        t = time.perf_counter()
        r = c.get(f"/api/review/picture/{pid}/{view}.png")
        first[view] = time.perf_counter() - t
        assert r.status_code == 200, (view, r.json)
    cached = timed(lambda: c.get(f"/api/review/picture/{pid}/joined-relief.png"))
    print(f"review pictures, fragments {shapes[0]} and {shapes[1]} px:")
    for view, s in first.items():
        print(f"  {view:14s} first view {1000 * s:8.1f} ms")
    print(f"  all four, first view       {1000 * sum(first.values()):8.1f} ms; cached {1000 * cached:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
