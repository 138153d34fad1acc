"""normals_from_map: the import policy on top of common.rgbn.io's normal-map checks (photographs
refused, OpenGL vs DirectX by integrability, a contradicted declaration refused)."""

from __future__ import annotations

import numpy as np
import pytest

from common.imports import ImportRefused
from common.imports.normals import normals_from_map
from common.rgbn.io import encode_normal_map


def _surface_normals(h=200, w=260, amp=6.0):
    """Analytic normals (x right, y up) of a bumpy height field; returns normals and the disc mask."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xx, -yy                      # y up
    z = amp * np.sin(x / 13.0) * np.cos(y / 17.0) + 0.002 * x * y
    zx = amp / 13.0 * np.cos(x / 13.0) * np.cos(y / 17.0) + 0.002 * y
    zy = -amp / 17.0 * np.sin(x / 13.0) * np.sin(y / 17.0) + 0.002 * x
    n = np.dstack([-zx, -zy, np.ones_like(z)])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    mask = (xx - w / 2) ** 2 / (0.45 * w) ** 2 + (yy - h / 2) ** 2 / (0.45 * h) ** 2 < 1
    return n.astype(np.float32), mask


def _angle_deg(a, b):
    """Angle between unit vectors, accurate near 0 (atan2 of cross and dot, float64)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(axis=-1)))


def _encode(n, mask, convention, bits):
    full = 255 if bits == 8 else 65535
    rgb = np.round(encode_normal_map(n, mask, convention) * full)
    return np.dstack([rgb, mask * full]).astype(np.uint8 if bits == 8 else np.uint16), float(full)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("stored", ["opengl", "directx"])
def test_declared_convention_decodes_to_the_true_normals(bits, stored):
    n, mask = _surface_normals()
    px, full = _encode(n, mask, stored, bits)
    got, m, info = normals_from_map(px, full, convention=stored)
    np.testing.assert_array_equal(m, mask)
    err = _angle_deg(got[mask], n[mask])
    # half a quantisation step on each of three components: sqrt(3) / full_scale radians at most
    assert err.max() < np.degrees(np.sqrt(3) / (255 if bits == 8 else 65535))
    assert info["convention"] == stored


@pytest.mark.parametrize("stored", ["opengl", "directx"])
def test_auto_tells_directx_from_opengl_and_a_wrong_declaration_is_refused(stored):
    n, mask = _surface_normals()
    px, full = _encode(n, mask, stored, 8)
    got, _, info = normals_from_map(px, full, convention="auto")
    assert info["convention"] == stored
    assert np.abs(got[mask] - n[mask]).max() < 0.02
    other = "directx" if stored == "opengl" else "opengl"
    with pytest.raises(ImportRefused, match=f"declared {other} but the map reads as {stored}"):
        normals_from_map(px, full, convention=other)


def test_flat_map_cannot_tell_the_convention_but_is_accepted_when_declared():
    n = np.zeros((100, 120, 3), np.float32)
    n[..., 2] = 1
    n[40:60, 50:70] = (0.2, 0.1, np.sqrt(1 - 0.05))   # a little tilted patch: too little relief
    px, full = _encode(n, np.ones(n.shape[:2], bool), "opengl", 16)
    with pytest.raises(ImportRefused, match="cannot tell OpenGL from DirectX"):
        normals_from_map(px, full, convention="auto")
    assert normals_from_map(px, full, convention="opengl")[2]["convention"] == "opengl"


def test_a_photograph_is_not_a_normal_map():
    rng = np.random.default_rng(0)
    h, w = 150, 200
    yy, xx = np.mgrid[0:h, 0:w]
    # a fresco photograph: ochre and red paint, shading, noise (blue well below half scale)
    photo = np.dstack([170 + 40 * np.sin(xx / 20), 110 + 30 * np.cos(yy / 15), 60 + 20 * np.sin((xx + yy) / 30)])
    photo = np.clip(photo + rng.normal(0, 8, photo.shape), 0, 255).astype(np.uint8)
    with pytest.raises(ImportRefused, match="it does not look like a normal map.*photograph"):
        normals_from_map(photo, 255.0)
    grey = np.full((h, w, 3), 128, np.uint8)       # decodes to zero vectors
    with pytest.raises(ImportRefused, match="almost no pixel decodes to a unit vector"):
        normals_from_map(grey, 255.0)


def test_black_background_is_outside_the_mask():
    n, mask = _surface_normals()
    rgb = np.round(encode_normal_map(n, mask, "opengl") * 65535).astype(np.uint16)   # no alpha, 0 outside
    _, m, _ = normals_from_map(rgb, 65535.0)
    np.testing.assert_array_equal(m, mask)


def test_bad_arguments():
    with pytest.raises(ValueError, match="convention"):
        normals_from_map(np.zeros((4, 4, 3), np.uint8), 255.0, convention="vulkan")
    with pytest.raises(ValueError, match="pixels must be"):
        normals_from_map(np.zeros((4, 4), np.uint8), 255.0)
