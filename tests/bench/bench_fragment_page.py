"""Benchmark of the fragment page (``/fragments/<id>``) on a large face, in headless Chromium.

    python tests/bench/bench_fragment_page.py [--width 4000 --height 3000] [--dpi 600] [--frames 30]

A synthetic relief face of width x height pixels (default 12 Mpx) is stored, ``tessera web
--no-scanner`` serves it as its own process, and Debian's Chromium (software GL: SwiftShader on a
machine without a GPU) opens the page. Prints:

* time to first picture — from navigation start to the first drawn tiles (any level: the
  one-tile top level stands in for the rest), to the first tile of the level the view needs, and to
  all of them — for a face never opened (its relight fields are computed on these first requests;
  the web server's CPU seconds beside it), for the face with its tiles cut, opened ``--opens``
  times each in a new browser (nothing in its HTTP cache; median), and for the next fragment of a
  browsing session (the page's scripts cached, that face's tiles cut on arrival but never fetched);
  each open waits until the web server is idle;
* the relighting frame time: a full redraw with another light, finished on the GPU (1-pixel
  readPixels), mean of ``--frames``, per style, at the whole-face view and at 1:1;
* the tile cost: server CPU per level-0 tile (cold), tile bytes, the cache's size on storage, and
  cutting every level but 0 ahead of a first view (``RelightCache.cut(min_level=1)``).

Targets (issue 17): first picture <= 1 s; frame <= 16 ms on a GPU by design (no per-frame uploads:
``uploads during frames`` must be 0); tiles cut once and cached.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

STYLES = ("albedo", "raking", "lambertian", "specular", "normal_unsharp", "exaggerated", "mean_curvature")


def cpu_of(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_idle(pid: int, quiet_s: float = 1.0, timeout_s: float = 120.0) -> None:
    """Wait until process ``pid`` has used under 5 % of a CPU for ``quiet_s`` (the web server done
    with the previous page's requests: its auto contrast, background cuts)."""
    t_end = time.perf_counter() + timeout_s
    while time.perf_counter() < t_end:
        c = cpu_of(pid)
        time.sleep(quiet_s)
        if cpu_of(pid) - c < 0.05 * quiet_s:
            return


def folder_bytes(path: Path) -> tuple[int, int]:
    files = [p for p in path.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=3000)
    ap.add_argument("--dpi", type=float, default=600.0)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--opens", type=int, default=5, help="opens of the cut face, each in a new browser")
    args = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from common.rgbn.image import save_rgbn
    from common.store import Store
    from tests.web.viewer_support import CHROMIUM, CHROMIUM_ARGS, WebProcess, open_viewer, show_one_to_one, \
        relief_face

    print(f"load average {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t, c = time.perf_counter(), time.process_time()
        image = relief_face(args.height, args.width, dpi=args.dpi)
        store = Store(root / "storage")
        save_rgbn(store, "fragments/B-1/rgbn/front-bench.h5", image)
        save_rgbn(store, "fragments/B-2/rgbn/front-bench.h5", image)   # the next fragment of a session
        del image
        from common.web.relight import RelightCache

        t, c = time.perf_counter(), time.process_time()
        RelightCache(store, "fragments/B-2/rgbn/front-bench.h5").cut(min_level=1)   # as the renderer does on arrival
        print(f"B-2's relight tiles cut ahead (levels >= 1) in {time.perf_counter() - t:.1f} s wall, "
              f"{time.process_time() - c:.1f} s CPU")
        print(f"face {args.width} x {args.height} px ({args.width * args.height / 1e6:.1f} Mpx) at {args.dpi:g} dpi "
              f"stored in {time.perf_counter() - t:.1f} s wall, {time.process_time() - c:.1f} s CPU")
        web = WebProcess(root).start()
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                def open_page(context, fid, label):
                    wait_idle(web.proc.pid)
                    cpu0 = cpu_of(web.proc.pid)
                    page = context.new_page(viewport={"width": 1280, "height": 900}, bypass_csp=True) \
                        if hasattr(context, "new_context") else context.new_page()
                    t = time.perf_counter()
                    open_viewer(page, f"{web.url}/fragments/{fid}", timeout_ms=600_000)
                    wall = time.perf_counter() - t
                    s = page.evaluate("() => tesseraViewer.stats")
                    lv = page.evaluate("() => [tesseraViewer.level(), tesseraViewer.levels.length]")
                    print(f"{label}: first picture {s['firstPictureMs']:.0f} ms, first tile of the level the "
                          f"view needs {s['firstTileMs']:.0f} ms, all of them {s['completeMs']:.0f} ms "
                          f"after navigation start (level {lv[0]} of {lv[1]}, {s['tilesLoaded']} tiles); "
                          f"test wall {wall:.2f} s; server CPU {cpu_of(web.proc.pid) - cpu0:.2f} s")
                    nav = page.evaluate("() => performance.getEntriesByType('navigation')[0].domContentLoadedEventEnd")
                    print(f"     page parsed {nav:.0f} ms, viewer init {s['initMs']:.0f} ms, "
                          f"OpenSeadragon started {s['contextMs']:.0f} ms")
                    return page, s["firstPictureMs"]

                # a face never opened: its relight fields are computed on these first requests
                browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                page, _ = open_page(browser, "B-1", "never-cut face, new browser")
                # tiles cut: a new browser each time (nothing in its HTTP cache), the server idle
                firsts = []
                for i in range(args.opens):
                    page.close()
                    browser.close()
                    browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                    page, ms = open_page(browser, "B-1", f"tiles cut, new browser ({i + 1}/{args.opens})")
                    firsts.append(ms)
                print(f"first picture, tiles cut, new browser: median {np.median(firsts):.0f} ms of {len(firsts)} "
                      f"(min {min(firsts):.0f}, max {max(firsts):.0f})")
                # the next fragment in a browsing session: the page's scripts in the HTTP cache (static
                # URLs are versioned and immutable), the face's tiles cut but never fetched by it
                context = browser.new_context(viewport={"width": 1280, "height": 900}, bypass_csp=True)
                first, _ = open_page(context, "B-1", "a first fragment in a new browsing session")
                nxt, ms = open_page(context, "B-2", "the next fragment, same session")
                print(f"first picture, the next fragment in a session: {ms:.0f} ms")
                first.close()
                nxt.close()
                context.close()
                print(f"canvas {page.evaluate('() => [tesseraViewer.canvas.width, tesseraViewer.canvas.height]')}")
                for style in ("raking", "exaggerated"):
                    cpu0 = cpu_of(web.proc.pid)
                    ms = page.evaluate(f"""async () => {{ const v = tesseraViewer, t = performance.now();
                        const r = await fetch(v.base + '/auto?style={style}&values=' + encodeURIComponent(JSON.stringify(v.values['{style}'])));
                        await r.json(); return performance.now() - t; }}""")
                    print(f"auto contrast, {style}: {ms:.0f} ms, server CPU {cpu_of(web.proc.pid) - cpu0:.2f} s")
                for view in ("whole face", "1:1"):
                    if view == "1:1":
                        cpu0 = cpu_of(web.proc.pid)
                        t = time.perf_counter()
                        page.evaluate("""() => { const v = tesseraViewer;
                            v.view = {cx: v.info.width / 2, cy: v.info.height / 2, zoom: 1}; v.render(); }""")
                        show_one_to_one(page, page.evaluate("() => tesseraViewer.canvas.width / 2 - tesseraViewer.info.width / 2"),
                                        page.evaluate("() => tesseraViewer.canvas.height / 2 - tesseraViewer.info.height / 2"))
                        n0 = page.evaluate("() => tesseraViewer.stats.tilesLoaded")
                        print(f"zoom to 1:1 at the centre (cold level-0 tiles): {time.perf_counter() - t:.2f} s wall, "
                              f"server CPU {cpu_of(web.proc.pid) - cpu0:.2f} s, tiles loaded so far {n0}")
                    for style in STYLES:
                        page.evaluate(f"() => tesseraViewer.setStyle('{style}')")
                        before = page.evaluate("() => tesseraViewer.stats.tilesLoaded")
                        ms = page.evaluate(f"() => tesseraViewer.frameTime({args.frames})")
                        after = page.evaluate("() => tesseraViewer.stats.tilesLoaded")
                        print(f"  frame {view:10s} {style:15s} {ms:6.1f} ms (uploads during frames: {after - before})")
                browser.close()
            folder = store.root / "fragments/B-1/viewer"
            n, b = folder_bytes(folder)
            print(f"relight cache on storage: {n} files, {b / 1e6:.1f} MB")
            level0 = sorted((folder).glob("*/0/*.bin.gz"))
            if level0:
                print(f"level-0 tile: {np.mean([p.stat().st_size for p in level0]) / 1e3:.0f} kB on average "
                      f"({len(level0)} cut)")
            # server CPU per level-0 tile, measured in this process on a fresh cache
            from common.web.relight import RelightCache

            cache = RelightCache(store, "fragments/B-1/rgbn/front-bench.h5")
            cache.folder += "-bench"
            cache.params()
            c, t = time.process_time(), time.perf_counter()
            for col in range(4):
                cache.tile_path(0, 5, col)
            print(f"level-0 tile cut: {(time.perf_counter() - t) / 4:.2f} s wall, "
                  f"{(time.process_time() - c) / 4:.2f} s CPU each (mean of 4)")
            # cutting ahead of a first view: every level but 0, coarse levels whole from one read
            ahead = RelightCache(store, "fragments/B-1/rgbn/front-bench.h5")
            ahead.folder += "-ahead"
            ahead.params()
            c, t = time.process_time(), time.perf_counter()
            n = ahead.cut(min_level=1)
            files, size = folder_bytes(store.root / ahead.folder)
            print(f"cut ahead (levels >= 1): {n} tiles in {time.perf_counter() - t:.1f} s wall, "
                  f"{time.process_time() - c:.1f} s CPU, {size / 1e6:.0f} MB")
        finally:
            web.stop()
    print(f"peak RSS of this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3:.0f} MB; "
          f"load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
