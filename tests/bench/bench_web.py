"""Benchmark of the web pages' server side: what a page waits for.

    python tests/bench/bench_web.py [--fragments 500] [--proposals 10000] [--dpi 300]
    python tests/bench/bench_web.py --only catalogue [--catalogue 10000]
    python tests/bench/bench_web.py --only tiles [--tile-mpx 12,50]

Prints, each the median of several requests through Flask's test client (no network):
* ``/api/bench`` with N fragments scanned today (the bench page's live poll: storage tree walk);
* ``/api/review/queue`` with M proposals in the matcher's SQLite store;
* the four review pictures of one proposal between two fragments of a synthetic fresco at the
  given dpi (first request: render; second: cache).
Targets: live poll and queue well under 0.5 s; a proposal's pictures under 2 s (first view).

``--only catalogue``: N fragments on storage (small faces with importer metadata, some scanned only,
proposals between some), the catalogue index built from storage (time and CPU), then the first
page of ``/api/catalogue`` and each filter (text, state, colour, joins, a deep page). Targets: first
page and filters <= 300 ms at 10,000 fragments.

``--only tiles``: a face of each size (synthetic, smooth albedo and normals) cut into its tile
pyramid: wall and CPU time, tiles written, peak memory of numpy arrays during the cut
(``tracemalloc``), and a IIIF region request served from the tiles.
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
    ap.add_argument("--only", choices=("pages", "catalogue", "tiles"), help="run one part (default: pages)")
    ap.add_argument("--catalogue", type=int, default=10000, help="fragments in the catalogue benchmark")
    ap.add_argument("--tile-mpx", default="12,50", help="face sizes of the tile benchmark, megapixels")
    args = ap.parse_args()
    if args.only == "catalogue":
        return bench_catalogue(args.catalogue)
    if args.only == "tiles":
        return bench_tiles([float(v) for v in args.tile_mpx.split(",")])
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


def cpu_timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - t, time.process_time() - c


def bench_catalogue(n: int) -> int:
    import json
    import os

    from common.rgbn.image import RGBNImage
    from common.web.catalogue import Catalogue

    print(f"load average at start: {os.getloadavg()}")
    root = Path(tempfile.mkdtemp(prefix="tessera-bench-catalogue-"))
    store = Store(root)
    rng = np.random.default_rng(1)
    palette = np.array([[0.6, 0.05, 0.04], [0.05, 0.1, 0.5], [0.6, 0.45, 0.1], [0.7, 0.7, 0.65], [0.1, 0.35, 0.1]],
                       np.float32)

    def write():
        for i in range(n):
            fid = f"W{i:05d}"
            if i % 10 == 9:   # scanned, not solved yet
                d = root / "fragments" / fid / "scans"
                d.mkdir(parents=True)
                (d / "scans-0.h5").write_bytes(b"")
                continue
            albedo = np.broadcast_to(palette[i % len(palette)] * rng.uniform(0.8, 1.2), (32, 40, 3))
            meta = {"inventory": f"INV-{i:05d}", "find_spot": f"Room {i % 37}", "context": f"US {i % 211}",
                    "date": ("1st c. AD", "2nd c. AD", "Augustan")[i % 3], "notes": "painted border" if i % 7 else ""}
            save_rgbn(store, f"fragments/{fid}/rgbn/front-{i:016x}.h5",
                      RGBNImage(albedo, np.ones((32, 40), bool), 300.0, attrs={"metadata": json.dumps(meta)}))
    _, wall, cpu = cpu_timed(write)
    print(f"{n} fragments written to storage: {wall:.1f} s wall, {cpu:.1f} s CPU")
    db_path = root / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        props = {}
        for k in range(n):
            a, b = sorted(rng.choice(n, 2, replace=False))
            props[(a, b)] = Proposal(f"W{a:05d}", f"W{b:05d}", float(rng.random()), "bench")
        db.upsert(list(props.values()))
        for (a, b) in list(props)[: n // 20]:
            db.record_verdict(f"W{a:05d}", f"W{b:05d}", "confirmed", by="bench")
    cat = Catalogue(root / "web" / "catalogue.sqlite", store, proposals=db_path)
    count, wall, cpu = cpu_timed(cat.rebuild)
    print(f"catalogue rebuilt from storage: {count} fragments in {wall:.1f} s wall, {cpu:.1f} s CPU "
          f"({1000 * wall / count:.1f} ms a fragment); load {os.getloadavg()[0]:.1f}")
    app = web.create_app(token=TOKEN, store_root=root, catalogue=cat)
    c = app.test_client()
    print(f"catalogue of {count} fragments (median of 5 requests, Flask test client; CPU in brackets):")
    for label, url in (("first page (50)", "/api/catalogue"),
                       ("text 'room 12'", "/api/catalogue?q=room%2012"),
                       ("text 'INV-0999'", "/api/catalogue?q=INV-0999"),
                       ("state=scanned", "/api/catalogue?state=scanned"),
                       ("colour=blue", "/api/catalogue?colour=blue"),
                       ("joins=confirmed", "/api/catalogue?joins=confirmed"),
                       ("colour+joins+text", "/api/catalogue?colour=red&joins=pending&q=augustan"),
                       ("page 150 of 200", "/api/catalogue?page=150"),
                       ("one fragment", "/api/catalogue/W00042"),
                       ("thumbnail", "/api/catalogue/W00042/thumb.png")):
        r = c.get(url)
        assert r.status_code == 200, (url, r.status_code)
        c0 = time.process_time()
        wall = timed(lambda: c.get(url))
        cpu = (time.process_time() - c0) / 5
        total = r.json.get("total") if r.is_json and isinstance(r.json, dict) else None
        print(f"  {label:20s} {1000 * wall:7.1f} ms  ({1000 * cpu:6.1f} ms CPU)"
              + (f"  {total} match" if total is not None else ""))
    print(f"load average at end: {os.getloadavg()}")
    return 0


def bench_tiles(sizes_mpx: list[float]) -> int:
    import os
    import tracemalloc

    import cv2

    from common.rgbn.image import RGBNImage
    from common.web import iiif
    from common.web.tiles import TileCache

    print(f"load average at start: {os.getloadavg()}")
    root = Path(tempfile.mkdtemp(prefix="tessera-bench-tiles-"))
    store = Store(root)
    rng = np.random.default_rng(2)
    for mpx in sizes_mpx:
        h = int(np.sqrt(mpx * 1e6 * 3 / 4))
        w = int(mpx * 1e6 / h)
        small = rng.random((h // 64 + 2, w // 64 + 2, 3)).astype(np.float32)
        albedo = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)
        slope = cv2.resize(rng.normal(0, 0.3, (h // 32 + 2, w // 32 + 2, 2)).astype(np.float32), (w, h))
        normals = np.dstack([slope, np.ones((h, w), np.float32)])
        del slope, small
        normals /= np.linalg.norm(normals, axis=2, keepdims=True)
        yy, xx = np.ogrid[0:h, 0:w]
        mask = ((yy - h / 2) / (0.48 * h)) ** 2 + ((xx - w / 2) / (0.48 * w)) ** 2 < 1
        rel = f"fragments/T{mpx:g}/rgbn/front-{int(mpx * 1000):016x}.h5"
        _, wall, cpu = cpu_timed(lambda: save_rgbn(store, rel, RGBNImage(albedo, mask, 600.0, normals=normals)))
        size = store.path(rel).stat().st_size / 1e6
        del albedo, normals, mask
        print(f"{mpx:g} Mpx face ({w} x {h}) written: {size:.0f} MB, {wall:.1f} s wall, {cpu:.1f} s CPU")
        cache = TileCache(store)
        tracemalloc.start()
        info, wall, cpu = cpu_timed(lambda: cache.pyramid(rel))
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
        tiles_mb = sum(p.stat().st_size for p in store.path(f"fragments/T{mpx:g}/tiles").rglob("*.png")) / 1e6
        print(f"  pyramid cut: {info['tiles']} tiles ({tiles_mb:.0f} MB, {len(info['levels'])} levels) in "
              f"{wall:.1f} s wall, {cpu:.1f} s CPU; peak numpy memory {peak:.0f} MB "
              f"(the face in float32 would be {h * w * 28 / 1e6:.0f} MB); load {os.getloadavg()[0]:.1f}")
        _, wall2, _ = cpu_timed(lambda: cache.pyramid(rel))
        req = iiif.parse_request("pct:25,25,50,50", "!1024,1024", "0", "default.jpg", w, h)
        px, wall3, cpu3 = cpu_timed(lambda: iiif.encode(iiif.render_request(
            req, info["levels"], lambda lv, y0, y1, x0, x1: cache.region(rel, "albedo", lv, y0, y1, x0, x1)), "jpg"))
        print(f"  second request of the pyramid: {1000 * wall2:.1f} ms; IIIF pct:25,25,50,50 at !1024,1024 jpg: "
              f"{1000 * wall3:.0f} ms ({1000 * cpu3:.0f} ms CPU)")
    print(f"load average at end: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
