"""On-demand check: museum IIIF viewers (Mirador 4, Universal Viewer 4) open a fragment's manifest
from ``tessera web`` and draw its tiles. Not part of the test suite; needs the npm registry.

    python tests/bench/check_iiif_viewers.py [--viewer mirador|uv|both] [--shots docs/web]

What it does, each time from nothing:

1. ``npm pack mirador@4`` (and/or ``universalviewer@4``) into a temporary folder and unpacks it
   (npm: ``apt-get install -y nodejs npm``); nothing of it is installed for the station, which
   loads nothing from outside;
2. stores a synthetic relief face (2000 x 1300 px, front, and a back face) and starts
   ``tessera web --no-scanner`` as its own process on loopback;
3. writes a small HTML page that loads the viewer's bundle and opens the station's manifest URL,
   and serves it from *another* localhost port (another origin, as a museum site would be: the
   station's CORS headers are what lets it read ``info.json`` and the tiles);
4. opens the page in Debian's Chromium (headless, Playwright), waits until tiles
   (``/iiif/image/<id>/<x,y,w,h>/<size>/0/default.<png|jpg>``) have been answered by the station and the
   fragment's colours are on the screen (its saturated red patch, counted in a screenshot), and
   saves the screenshot (the first canvas: the front face) (``<shots>/mirador.png``, ``<shots>/uv.png``); then zooms in with the
   mouse wheel until full-resolution tiles (size = region) are answered and drawn
   (``<shots>/<viewer>-zoomed.png``).

Prints the IIIF requests the viewer made and their statuses, browser console errors, and exits
non-zero when a viewer failed (no tile requested or drawn, a failed IIIF request).
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import re
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

VIEWERS = {
    # npm package spec, the bundle inside the package, the page's body (MANIFEST is replaced)
    "mirador": ("mirador@4", "dist/mirador.min.js", """
<div id="viewer" style="position:absolute; inset:0"></div>
<script src="pkg/dist/mirador.min.js"></script>
<script>
  window.viewer = Mirador.viewer({
    id: "viewer",
    windows: [{manifestId: MANIFEST, thumbnailNavigationPosition: "far-bottom"}],
    window: {allowClose: false, sideBarOpen: false},
    workspaceControlPanel: {enabled: false},
    // tiles fetched in CORS mode, so OpenSeadragon may draw them with WebGL (else: "tainted data")
    osdConfig: {crossOriginPolicy: "Anonymous"},
  });
</script>"""),
    "uv": ("universalviewer@4", "dist/umd/UV.js", """
<link rel="stylesheet" href="pkg/dist/uv.css">
<div id="uv" class="uv" style="width:100vw; height:100vh"></div>
<script src="pkg/dist/umd/UV.js"></script>
<script>
  window.viewer = UV.init("uv", {manifest: MANIFEST, embedded: true});
</script>"""),
}

# a tile request: region x,y,w,h (not full), any size, rotation 0, any quality and format
TILE = re.compile(r"/iiif/image/[^/]+/\d+,\d+,(\d+),(\d+)/\^?(\d*),(\d*)/0/\w+\.(jpg|png)$")
# the relief face's saturated red patch (linear (0.6, 0.08, 0.05)) in display sRGB
RED = np.array([203, 79, 63])


def npm_pack(spec: str, into: Path) -> Path:
    """``npm pack <spec>`` into ``into`` and unpack it; the package folder."""
    out = subprocess.run(["npm", "pack", spec, "--json"], cwd=into, check=True, capture_output=True, text=True)
    info = json.loads(out.stdout)[0]
    with tarfile.open(into / info["filename"]) as tar:
        tar.extractall(into, filter="data")
    print(f"[npm] {info['name']}@{info['version']} ({info['size'] / 1e6:.1f} MB packed)")
    return into / "package"


class Site:
    """A static site on its own localhost port (the 'museum' origin)."""

    def __init__(self, root: Path):
        handler = functools.partial(_Quiet, directory=str(root))
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def stop(self):
        self.httpd.shutdown()


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def full_resolution(url: str) -> bool:
    """A tile of the full-resolution level: the size asked is the region's."""
    m = TILE.search(url)
    return bool(m) and m.group(1) == m.group(3) and m.group(2) in (m.group(4), "")


def red_pixels(png: Path) -> int:
    import cv2

    img = cv2.cvtColor(cv2.imread(str(png), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(int)
    return int((np.abs(img - RED).max(axis=2) <= 24).sum())


def check(viewer: str, station_url: str, work: Path, shots: Path, timeout_s: float = 90.0) -> bool:
    from playwright.sync_api import sync_playwright

    from tests.web.viewer_support import CHROMIUM, CHROMIUM_ARGS, screenshot

    spec, bundle, body = VIEWERS[viewer]
    site_dir = work / viewer
    site_dir.mkdir()
    pkg = npm_pack(spec, site_dir)
    pkg.rename(site_dir / "pkg")
    if not (site_dir / "pkg" / bundle).exists():
        print(f"[{viewer}] no {bundle} in the package: {sorted(p.name for p in (site_dir / 'pkg' / 'dist').iterdir())}")
        return False
    manifest = f"{station_url}/iiif/presentation/F-1/manifest"
    (site_dir / "index.html").write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>{viewer}</title>"
        f"<link rel='icon' href='data:,'></head><body style='margin:0'>"
        f"{body.replace('MANIFEST', json.dumps(manifest))}</body></html>")
    site = Site(site_dir)
    iiif, console, others = [], [], []
    shot = shots / f"{viewer}.png"
    ok = False
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 860})
            page.on("console", lambda m: console.append(f"{m.type}: {m.text}") if m.type in ("error", "warning") else None)
            page.on("pageerror", lambda e: console.append(f"pageerror: {e}"))
            page.on("requestfailed", lambda r: iiif.append((r.url, f"failed: {r.failure}")) if "/iiif/" in r.url else None)
            page.on("response", lambda r: iiif.append((r.url, r.status)) if "/iiif/" in r.url else
                    others.append((r.url, r.status)) if r.status >= 400 else None)
            t0 = time.monotonic()
            page.goto(f"{site.url}/index.html")
            tiles, red = [], 0
            while time.monotonic() - t0 < timeout_s:
                page.wait_for_timeout(1000)
                tiles = [u for u, s in iiif if TILE.search(u) and s == 200]
                if tiles:
                    page.wait_for_load_state("networkidle")
                    page.wait_for_timeout(1500)              # the viewer's fade-in of the tiles
                    screenshot(page, shot)
                    red = red_pixels(shot)
                    if red > 2000:
                        break
            first_s = time.monotonic() - t0
            # zoom in about the middle (mouse wheel) until full-resolution tiles are asked for
            page.mouse.move(760, 450)
            for _ in range(12):
                page.mouse.wheel(0, -300)
                page.wait_for_timeout(400)
            page.wait_for_load_state("networkidle")
            page.wait_for_timeout(1500)
            # (a viewer may have fetched some already, to have them ready: all are counted)
            level0 = [u for u, s in iiif if full_resolution(u) and s == 200]
            zoom_shot = shots / f"{viewer}-zoomed.png"
            screenshot(page, zoom_shot)
            zoom_red = red_pixels(zoom_shot)
            print(f"[{viewer}] zoomed in: {len(level0)} full-resolution tiles answered, {zoom_red} px of red on screen")
            print(f"[{viewer}] first view after {first_s:.1f} s: {len(tiles)} tile requests answered, "
                  f"{red} px of the fragment's red patch on screen -> {shot.relative_to(REPO) if shot.is_relative_to(REPO) else shot}")
            browser.close()
        bad = [(u, s) for u, s in iiif if s != 200]
        for u, s in iiif[:12]:
            print(f"    {s}  {u.replace(station_url, '')}")
        if len(iiif) > 12:
            print(f"    … {len(iiif) - 12} more")
        for u, s in bad:
            print(f"  FAILED {s}  {u}")
        for u, s in others:
            print(f"  (not IIIF) {s}  {u}")
        for line in console[:20]:
            print(f"  console {line}")
        ok = bool(tiles) and red > 2000 and bool(level0) and zoom_red > 2000 and not bad
    finally:
        site.stop()
    print(f"[{viewer}] {'OK' if ok else 'FAILED'}")
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--viewer", choices=("mirador", "uv", "both"), default="both")
    ap.add_argument("--shots", type=Path, default=REPO / "docs" / "web", help="folder for <viewer>.png")
    args = ap.parse_args(argv)

    from common.rgbn.image import save_rgbn
    from common.store import Store
    from tests.web.viewer_support import WebProcess, relief_face

    args.shots.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="tessera-iiif-viewers-") as tmp:
        work = Path(tmp)
        store = Store(work / "storage")
        save_rgbn(store, "fragments/F-1/rgbn/front-k1.h5", relief_face(1300, 2000, dpi=600.0))
        save_rgbn(store, "fragments/F-1/rgbn/back-k3.h5", relief_face(500, 700, dpi=600.0, seed=3))
        web = WebProcess(work).start()
        try:
            names = ("mirador", "uv") if args.viewer == "both" else (args.viewer,)
            results = {name: check(name, web.url, work, args.shots) for name in names}
        finally:
            web.stop()
    print("  ".join(f"{k}: {'OK' if v else 'FAILED'}" for k, v in results.items()))
    return 0 if all(results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
