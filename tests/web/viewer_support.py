"""What the fragment-page tests share: an analytic RGBN face, ``tessera web`` as its own process on a
store holding it, and Debian's Chromium driven by Playwright (never ``playwright install``)."""

from __future__ import annotations

import importlib.util
import os
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from .conftest import TOKEN, free_port, wait_for

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = "/usr/bin/chromium"
# software GL (SwiftShader) is what headless Chromium has on a machine without a GPU
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]


def require_browser():
    if importlib.util.find_spec("playwright") is None:
        pytest.skip("browser tests need the pip package 'playwright' (pip install playwright)")
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"browser tests need Debian's Chromium at {CHROMIUM} (apt-get install -y chromium)")


def relief_face(h: int, w: int, *, dpi: float = 300.0, seed: int = 0, noise: float = 0.03):
    """An RGBN face with known relief: a height field (mm-free, in pixels) of ripples, a dome and a
    groove plus noise, its normals by finite differences; an elliptic mask; colour ramps and a
    saturated red patch (colours near the sRGB gamut's edge)."""
    from common.rgbn.image import RGBNImage

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    z = 2.5 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    z += 6.0 * np.exp(-((xx - 0.3 * w) ** 2 + (yy - 0.5 * h) ** 2) / (2 * 18.0 ** 2))
    z -= 4.0 * np.exp(-((xx - 0.7 * w) ** 2) / (2 * 3.0 ** 2))
    z += rng.normal(0.0, noise, z.shape)
    gy, gx = np.gradient(z)
    n = np.dstack([-gx, gy, np.ones_like(gx)])          # y up: rows grow downwards
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = ((xx - w / 2) ** 2 / (0.47 * w) ** 2 + (yy - h / 2) ** 2 / (0.46 * h) ** 2) < 1
    albedo = np.dstack([0.15 + 0.6 * (xx / w), 0.25 + 0.2 * np.sin(yy / 15.0), 0.55 - 0.4 * (yy / h)])
    albedo = np.clip(albedo, 0.0, 1.0).astype(np.float32)
    albedo[(xx > 0.5 * w) & (yy < 0.4 * h)] = (0.6, 0.08, 0.05)
    return RGBNImage(albedo=albedo, mask=mask, dpi=dpi, normals=n.astype(np.float32))


class WebProcess:
    """``tessera web --no-scanner`` on loopback over a storage root (no broker needed to read)."""

    def __init__(self, root: Path):
        self.root = root
        self.port = free_port()
        self.config = root / "station.toml"
        self.config.write_text(f"""
[storage]
root = "{root / 'storage'}"
[broker]
host = "127.0.0.1"
port = {free_port()}
feed_port = {free_port()}
[client]
timeout_s = 0.5
retries = 1
[scanner]
spool_dir = "{root / 'bench'}"
[services.web]
port = {self.port}
token = "{TOKEN}"
""")
        self.url = f"http://127.0.0.1:{self.port}"
        self.children = None

    def start(self) -> "WebProcess":
        self.children = children(self.config, self.root)
        wait_for_web(self.children.start("web", "web", "--no-scanner"), self.url, self.root / "web.log")
        return self

    @property
    def proc(self):
        """The ``tessera web`` process (its pid for CPU accounting)."""
        return self.children.procs["web"]

    def stop(self) -> None:
        if self.children is not None:
            self.children.stop(grace_s=10.0)


def children(config: Path, root: Path):
    """The station's own spawner (:class:`services.cli.station.Children`) for processes of a test
    station with this config; logs ``<root>/<name>.log``."""
    from services.cli.station import Children

    return Children(["--config", str(config)], root, env=dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1"))


def wait_for_web(proc, url: str, log: Path, timeout_s: float = 60) -> None:
    """Wait until ``tessera web`` (process ``proc``) answers ``/status``; its log if it exits first."""
    def answers():
        if proc.poll() is not None:
            raise AssertionError(f"tessera web exited: {log.read_text()[-2000:]}")
        try:
            return urllib.request.urlopen(url + "/status", timeout=2).status == 200
        except OSError:
            return False
    wait_for(answers, timeout_s, "tessera web to answer", interval=0.3)


def open_viewer(page, url: str, timeout_ms: int = 60_000) -> None:
    """Navigate to a fragment page and wait until its viewer has drawn every tile it needs."""
    page.goto(url)
    wait_complete(page, timeout_ms)


def wait_complete(page, timeout_ms: int = 60_000) -> None:
    page.wait_for_function("() => window.tesseraViewer && tesseraViewer.stats && tesseraViewer.stats.complete",
                           timeout=timeout_ms)


def show_one_to_one(page, x0: int, y0: int) -> None:
    """Put image pixel (0, 0) at canvas pixel (x0, y0), one image pixel per canvas pixel, and wait
    for the level-0 tiles."""
    page.evaluate(f"""() => {{ const v = tesseraViewer;
        v.view = {{cx: v.canvas.width / 2 - {x0}, cy: v.canvas.height / 2 - {y0}, zoom: 1}}; v.render(); }}""")
    page.wait_for_function("() => tesseraViewer.level() === 0 && (tesseraViewer.render(), tesseraViewer.stats.complete)",
                           timeout=60_000, polling=200)


def screenshot(page, path: Path, max_bytes: int = 300_000) -> None:
    """A screenshot of the page at ``path``, shrunk until it is under ``max_bytes`` (docs pictures)."""
    import cv2

    page.screenshot(path=str(path))
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    scale = 1.0
    while path.stat().st_size > max_bytes and scale > 0.3:
        scale *= 0.85
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(path), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
