"""IIIF's own Image API validator (PyPI ``iiif-validator``) against ``tessera web`` as its own process.

The validator needs its test image served: 1000 x 1000 px, 10 x 10 squares of 100 px whose colours
it knows (``ValidationInfo.colorInfo[x][y]``, x = column). It is stored here as a fragment face
(albedo = those sRGB colours in linear light, so the albedo tiles give them back), and every test the
validator has up to level 2 — the level ``info.json`` claims — plus the level-3 ones for the
features ``extraFeatures`` claims (mirroring, the profile and canonical link headers) runs against it.

Two of the validator's 3.0 checks contradict the Image API 3.0 text; for those the validator's own
checks run for every size form it gets right and the spec's rule is asserted for the other:

* ``size_noup`` asks ``!2000,3000`` of the 1000 x 1000 image and expects 400; §4.2 says ``!w,h`` returns
  an image "as large as possible but not larger than the extracted region, w or h": 1000 x 1000, 200.
* ``size_up`` expects ``^max`` to be the full 1000 x 1000; §4.2 says ``^max`` is the region "scaled to
  the maximum size permitted by maxWidth, maxHeight, or maxArea": here ``maxArea`` (16 Mpx).

(``quality_bitonal`` is a level-2 test in the validator, as in Image API 2.x; 3.0 makes ``bitonal``
optional. The server has it anyway, listed in ``extraQualities``.)
"""

from __future__ import annotations

import random

import numpy as np
import pytest

from common.web import iiif

from .viewer_support import WebProcess, relief_face

pytestmark = pytest.mark.slow      # ~15 s: a tessera web process and ~40 validator runs

IDENTIFIER = "V-1~front~albedo"
#: level-3 (optional) validator tests for features the server claims in extraFeatures
CLAIMED_EXTRAS = ("rot_mirror", "rot_mirror_180", "linkheader_profile", "linkheader_canonical")
#: validator tests whose expectations differ from the 3.0 text (see the module doc): checked below
AGAINST_THE_SPEC = ("size_noup", "size_up")


def validator_test_image():
    """The validator's test image as an RGBN face (flat normals)."""
    from iiif_validator.validator import ValidationInfo

    from common.rgbn.image import RGBNImage
    from common.rgbn.io import srgb_to_linear

    colours = np.array(ValidationInfo().colorInfo, np.float32) / 255.0            # [x][y] = [column][row]
    srgb = np.repeat(np.repeat(colours.transpose(1, 0, 2), 100, axis=0), 100, axis=1)
    normals = np.zeros_like(srgb)
    normals[..., 2] = 1.0
    return RGBNImage(srgb_to_linear(srgb).astype(np.float32), np.ones((1000, 1000), bool), 300.0,
                     normals=normals)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from common.rgbn.image import save_rgbn
    from common.store import Store

    root = tmp_path_factory.mktemp("iiif-validator")
    save_rgbn(Store(root / "storage"), "fragments/V-1/rgbn/front-v1.h5", validator_test_image())
    # a face whose sides are no multiple of the tile size, for the sizes and tiles info.json lists
    save_rgbn(Store(root / "storage"), "fragments/V-2/rgbn/front-v2.h5", relief_face(530, 700))
    web = WebProcess(root).start()
    try:
        yield web.url.removeprefix("http://")
    finally:
        web.stop()


def _api(server):
    from iiif_validator.validator import ImageAPI

    return ImageAPI(IDENTIFIER, server, "iiif/image", "http", "", "3.0", debug=False)


def _tests(max_level: int):
    from iiif_validator.validator import TestSuite, ValidationInfo

    listed = TestSuite(ValidationInfo()).list_tests("3.0")
    return sorted(name for name, t in listed.items()
                  if (t["level"] <= max_level or name in CLAIMED_EXTRAS) and name not in AGAINST_THE_SPEC)


def _run(server, name):
    from iiif_validator.validator import TestSuite, ValidationInfo

    random.seed(name)               # the validator picks squares and sizes at random: the same each run
    result = _api(server)
    TestSuite(ValidationInfo()).run_test(name, result)
    e = result.exception
    assert e is None, f"{name}: {e} (urls {result.urls}; status {getattr(e, 'status', None)})"
    return result


def test_the_claimed_level_is_level2():
    # if this changes, change the level the validator runs at below
    assert iiif.PROFILE == "level2"


@pytest.mark.parametrize("name", _tests(2))
def test_iiif_validator(server, name):
    _run(server, name)


def test_sizes_larger_than_the_region_need_the_caret_but_a_confining_box_never_errs(server):
    """``size_noup``: the validator's checks of ``w,h``, ``,h``, ``w,`` and ``pct:200`` (400 without
    ``^``), and §4.2's rule for ``!w,h`` (the region's size, not an error)."""
    from iiif_validator.tests.size_noup import Test_No_Size_Up
    from iiif_validator.validator import ValidationInfo

    test, result = Test_No_Size_Up(ValidationInfo()), _api(server)
    for size in ("1500,1500", ",1500", "1500,", "pct:200"):
        with pytest.raises(Exception):          # the validator's "fetch failed" path, which checks for 400
            result.get_image({"size": size})
        assert result.last_status == 400, size
        test.checkSize(result, size)
    img = result.get_image({"size": "!2000,3000"})
    assert result.last_status == 200 and img.size == (1000, 1000)
    assert ValidationInfo().do_test_square(img.crop((313, 513, 387, 587)), 3, 5, result)


def test_upscaling_with_the_caret(server):
    """``size_up``: the validator's checks of ``^w,h``, ``^,h``, ``^w,``, ``^pct:200``, ``^!w,h``, and
    §4.2's ``^max`` (the region scaled to ``maxArea``)."""
    from iiif_validator.tests.size_up import Test_Size_Up
    from iiif_validator.validator import ValidationInfo

    random.seed(3)
    test, result = Test_Size_Up(ValidationInfo()), _api(server)
    for want, size in (((1500, 1500), "^1500,1500"), ((1500, 1500), "^,1500"), ((1500, 1500), "^1500,"),
                       ((2000, 2000), "^pct:200"), ((500, 500), "^!2000,500"), ((2000, 2000), "^!2000,3000")):
        test.checkSize(result, want, size, f"size {size}")
    side = int(np.sqrt(iiif.MAX_AREA))
    img = result.get_image({"size": "^max", "format": "png"})
    assert img.size == (side, side) and side * side <= iiif.MAX_AREA
    test.checkSquares(img, side, result)


def test_the_link_headers_name_the_level2_profile_and_the_canonical_request(server):
    import urllib.request

    with urllib.request.urlopen(f"http://{server}/iiif/image/{IDENTIFIER}/pct:10,20,30,40/!100,100/!90/color.png") as r:
        link = r.headers["Link"]
    assert '<http://iiif.io/api/image/3/level2.json>;rel="profile"' in link
    assert f'<http://{server}/iiif/image/{IDENTIFIER}/100,200,300,400/75,100/!90/color.png>;rel="canonical"' in link
    with urllib.request.urlopen(f"http://{server}/iiif/image/{IDENTIFIER}/full/max/0/default.jpg") as r:
        assert f"/iiif/image/{IDENTIFIER}/full/max/0/default.jpg>;rel=\"canonical\"" in r.headers["Link"]


def test_every_size_and_tile_info_json_lists_is_served_at_that_size(server):
    """Compliance (Image API 3.0, §3.2 of the compliance document): "an image service whose Image
    Information response includes the sizes property must support requests for the sizes listed,
    and [with] the tiles property must support requests for the sizes implicit in the width, height
    and scaleFactors values given for tiles" — the tile requests as the 3.0 implementation notes
    (§3) compute them, partial tiles on the right and bottom edges included."""
    import io
    import json
    import urllib.request

    from PIL import Image

    base = f"http://{server}/iiif/image/V-2~front~albedo"
    with urllib.request.urlopen(f"{base}/info.json") as r:
        info = json.load(r)
    width, height = info["width"], info["height"]
    assert (width, height) == (700, 530)

    def fetch(path):
        with urllib.request.urlopen(f"{base}/{path}") as r:
            assert r.status == 200, path
            return Image.open(io.BytesIO(r.read())).size

    for size in info["sizes"]:
        assert fetch(f"full/{size['width']},{size['height']}/0/default.jpg") == (size["width"], size["height"])
    requests = 0
    for tiles in info["tiles"]:
        tw, th = tiles["width"], tiles.get("height", tiles["width"])
        for s in tiles["scaleFactors"]:
            for m in range(-(-height // (th * s))):
                for n in range(-(-width // (tw * s))):
                    xr, yr = n * tw * s, m * th * s
                    wr, hr = min(tw * s, width - xr), min(th * s, height - yr)
                    ws = tw if xr + tw * s <= width else (width - xr + s - 1) // s
                    hs = th if yr + th * s <= height else (height - yr + s - 1) // s
                    assert fetch(f"{xr},{yr},{wr},{hr}/{ws},{hs}/0/default.png") == (ws, hs)
                    requests += 1
    assert requests == 9 + 4 + 1          # scale factors 1, 2, 4: 3 x 3, 2 x 2 and 1 tile
