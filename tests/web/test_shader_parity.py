"""The viewer's shaders draw what the offline renderer draws.

Every style the fragment page's WebGL viewer shades (``services/web/static/viewer/<style>.frag``)
is drawn twice on the same analytic RGBN face with the same parameters: offline in Python
(:data:`common.render.recipes.STYLES`, with :func:`common.web.relight.offline_arguments`), and in
headless Chromium (software GL) from the tiles ``tessera web`` serves, at one image pixel per
canvas pixel, read back from the canvas. The contrast of each is the offline style's own "auto"
choice on that face. The mean absolute difference on the fragment must be <= 2/255 (issue 17).
The face is two tiles wide, so the seam between tiles is inside the comparison.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from .viewer_support import CHROMIUM, CHROMIUM_ARGS, WebProcess, open_viewer, relief_face, require_browser, \
    show_one_to_one

pytestmark = pytest.mark.slow

#: (style, values that differ from the viewer's defaults): every shading the viewer offers, in
#: grey and in colour where the offline style has both
CASES = [
    ("albedo", {"exposure": "none"}), ("albedo", {}),
    ("lambertian", {}), ("lambertian", {"colour": False}),
    ("raking", {}), ("raking", {"colour": True, "azimuth_deg": 200.0, "elevation_deg": 20.0}),
    ("specular", {}), ("specular", {"colour": False, "exponent": 60.0}), ("specular", {"lightness": "auto"}),
    ("normal_unsharp", {}), ("normal_unsharp", {"colour": True}),
    ("exaggerated", {}), ("exaggerated", {"colour": True, "exposure": "auto"}),
    ("mean_curvature", {}),
]
#: where image pixel (0, 0) is drawn on the canvas
X0, Y0 = 7, 5
LIMIT = 2.0   # mean absolute difference, in 1/255


#: the tilt of the whole face in the levelling test (a panel not square to the camera), degrees about y
TILT_DEG = 25.0


@pytest.fixture(scope="module")
def served_faces(tmp_path_factory):
    """``tessera web`` over two faces, P-1 (the analytic face) and T-1 (the same turned as a whole by TILT_DEG
    towards +x: its normals rotated about the y axis), and one Chromium (one Playwright per process);
    yields (browser, web, {id: image}, the analytic face)."""
    require_browser()
    from dataclasses import replace

    from playwright.sync_api import sync_playwright

    from common.rgbn.image import save_rgbn
    from common.store import Store

    root = tmp_path_factory.mktemp("parity")
    image = relief_face(180, 300)
    t = np.radians(TILT_DEG)
    turn = np.array([[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]], np.float32)
    faces = {"P-1": image, "T-1": replace(image, normals=(image.normals @ turn.T).astype(np.float32))}
    for fid, face in faces.items():
        save_rgbn(Store(root / "storage"), f"fragments/{fid}/rgbn/front-analytic.h5", face)
    web = WebProcess(root).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            yield browser, web, faces
            browser.close()
    finally:
        web.stop()


def _page_of(served_faces, fid: str):
    browser, web, faces = served_faces
    # bypass_csp: the test's own page.evaluate calls are eval to the page's CSP
    page = browser.new_page(viewport={"width": 1100, "height": 800}, bypass_csp=True)
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    open_viewer(page, f"{web.url}/fragments/{fid}")
    show_one_to_one(page, X0, Y0)
    return page, errors


@pytest.fixture(scope="module")
def parity_page(served_faces):
    page, errors = _page_of(served_faces, "P-1")
    yield page, served_faces[2]["P-1"], errors
    page.close()


@pytest.fixture(scope="module")
def tilted_page(served_faces):
    """The face turned as a whole, in the viewer: (page, the tilted image, the image as it was)."""
    page, _ = _page_of(served_faces, "T-1")
    yield page, served_faces[2]["T-1"], served_faces[2]["P-1"]
    page.close()


def _shader(page, style: str, values: dict, h: int, w: int) -> np.ndarray:
    px = page.evaluate(f"""() => {{ const v = tesseraViewer; v.setStyle({json.dumps(style)}, {json.dumps(values)});
        v.render(); return Array.from(v.pixels({X0}, {Y0}, {w}, {h})); }}""")
    return np.asarray(px, np.float64).reshape(h, w, 4)[..., :3]


def _offline(image, style: str, values: dict, params: dict) -> np.ndarray:
    from common.render.recipes import STYLES
    from common.web.relight import offline_arguments

    layer = STYLES[style].draw(image, **offline_arguments(style, values, params))
    return np.round(np.clip(layer.rgb, 0.0, 1.0) * 255.0)


def _values(page, image, style: str, extra: dict, params: dict) -> dict:
    """The viewer's defaults for ``style`` with ``extra``, its contrast chosen by the offline "auto"."""
    from common.web.relight import auto_contrast

    values = json.loads(page.evaluate(f"() => JSON.stringify(RelightViewer.STYLES[{json.dumps(style)}].defaults)"))
    values.update({k: v for k, v in extra.items() if v != "auto"})
    auto = {k: "auto" for k, v in extra.items() if v == "auto"}
    resolved = {k: v for k, v in auto_contrast(image, style, values, params).items() if k not in extra}
    if auto:   # a second contrast parameter (the colour's exposure of a colour variant)
        from common.render.recipes import STYLES
        from common.web.relight import offline_arguments

        kw = offline_arguments(style, {**values, **resolved}, params)
        kw.update(auto)
        layer = STYLES[style].draw(image, **kw)
        resolved.update({k: layer.resolved[k] for k in auto})
    values.update(resolved)
    return values


@pytest.mark.parametrize("style,extra", CASES, ids=[f"{s}-{i}" for i, (s, _) in enumerate(CASES)])
def test_shader_matches_offline_style(parity_page, style, extra):
    page, image, errors = parity_page
    params = page.evaluate("() => tesseraViewer.info")
    h, w = image.mask.shape
    values = _values(page, image, style, extra, params)
    offline = _offline(image, style, values, params)
    shader = _shader(page, style, values, h, w)
    assert not errors, errors
    on = image.mask
    assert offline[on].std() > 8.0, f"{style}: the offline picture is nearly flat; the comparison would prove nothing"
    diff = np.abs(shader - offline)[on]
    mad = float(diff.mean())
    print(f"\n{style} {extra}: mean |shader - offline| = {mad:.3f}/255, 99th percentile "
          f"{np.percentile(diff, 99):.1f}, max {diff.max():.0f}; values {values}")
    assert mad <= LIMIT, f"{style} {extra}: mean absolute difference {mad:.2f}/255 > {LIMIT}/255"
    # outside the fragment both draw the background (white)
    assert np.abs(shader[~on] - 255.0).max() <= 1.0


def test_the_comparison_sees_a_wrong_light(parity_page):
    """The same comparison with the shader's light turned by 90 degrees fails by far: the test can fail."""
    page, image, _ = parity_page
    params = page.evaluate("() => tesseraViewer.info")
    h, w = image.mask.shape
    values = _values(page, image, "lambertian", {"colour": False}, params)
    offline = _offline(image, "lambertian", values, params)
    turned = dict(values, light=[values["light"][0] + 90.0, values["light"][1]])
    shader = _shader(page, "lambertian", turned, h, w)
    mad = float(np.abs(shader - offline)[image.mask].mean())
    assert mad > 5 * LIMIT, f"a light turned by 90 degrees differs by only {mad:.2f}/255"


@pytest.mark.parametrize("style,extra", [("normal_unsharp", {"colour": True}),
                                         ("exaggerated", {"colour": True, "strength": 1.0, "exposure": "auto"})])
def test_the_shader_maps_colours_outside_the_gamut_as_offline(parity_page, style, extra):
    """Where the colour leaves sRGB's gamut (the face's saturated red lightened or exposed), both
    keep L* and hue and reduce the chroma (``enhance.gamut_map_lab``), pixel for pixel; clipping
    each channel instead (OpenCV's float Lab2RGB, what both did before) is far from either."""
    from unittest import mock

    from common.render import enhance

    page, image, errors = parity_page
    params = page.evaluate("() => tesseraViewer.info")
    h, w = image.mask.shape
    values = _values(page, image, style, extra, params)
    offline = _offline(image, style, values, params)
    with mock.patch.object(enhance, "_into_gamut", lambda rgb, lab: rgb):
        clipped = _offline(image, style, values, params)
    shader = _shader(page, style, values, h, w)
    assert not errors, errors
    mapped = image.mask & (np.abs(offline - clipped).max(axis=2) > 3)
    assert mapped.mean() > 0.01, f"{style}: only {mapped.mean():.4f} of the face leaves the gamut"
    to_offline = float(np.abs(shader - offline)[mapped].mean())
    to_clipped = float(np.abs(shader - clipped)[mapped].mean())
    print(f"\n{style} {extra}: {mapped.sum()} px mapped into the gamut; mean |shader - offline| there "
          f"{to_offline:.3f}/255, |shader - clipped| {to_clipped:.3f}/255")
    assert to_offline <= LIMIT
    assert to_clipped > 2 * LIMIT



@pytest.mark.parametrize("style,extra", [("raking", {}), ("lambertian", {"colour": False}), ("specular", {})])
def test_a_face_tilted_as_a_whole_is_lit_relative_to_its_own_plane(tilted_page, style, extra):
    """A near-flat face whose normals all lean one way (a panel not square to the camera; seen on a real RTI
    capture leaning 27°, whose raking view was black) is lit relative to the way it faces: the page's
    surface_normal is the tilt put in, the shader turns the light as the offline style turned by the same
    direction does (parity), and the picture is, within the levelling's estimate, that of the face untilted."""
    page, image, flat = tilted_page
    params = page.evaluate("() => tesseraViewer.info")
    t = np.radians(TILT_DEG)
    facing = np.array(params["surface_normal"])
    assert np.degrees(np.arccos(np.clip(facing @ [np.sin(t), 0.0, np.cos(t)], -1, 1))) < 2.0, facing
    h, w = image.mask.shape
    values = _values(page, image, style, extra, params)
    shader = _shader(page, style, values, h, w)
    on = image.mask
    offline = _offline(image, style, values, params)
    assert offline[on].std() > 8.0
    assert float(np.abs(shader - offline)[on].mean()) <= LIMIT
    if style == "specular":   # its half vector keeps the view as it is: lit, not the untilted face's highlights
        return
    # the same values on the face as it was, lit relative to its own plane (its relief leans it a little): the
    # same picture, within what the normals' smoothing (weighted by 1/n_z, which a tilt changes) moves
    from common.render.enhance import surface_normal

    untilted = _offline(flat, style, values, dict(params, surface_normal=surface_normal(flat.normals, flat.mask).tolist()))
    unlevelled = _offline(image, style, values, dict(params, surface_normal=None))
    near, far = (float(np.abs(x - untilted)[on].mean()) for x in (shader, unlevelled))
    print(f"\n{style}: |shader - untilted| {near:.2f}/255, |unlevelled - untilted| {far:.2f}/255")
    assert near <= 3 * LIMIT
    assert far > 5 * near          # without the levelling it is another picture (the check can fail)
