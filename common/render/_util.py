"""Small helpers shared by the render styles (private)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



@dataclass
class Layer:
    """One drawn layer: colour and coverage on the image's pixel grid.

    Attributes
    ----------
    rgb : (H, W, 3) float32
        Display colour in [0, 1].
    alpha : (H, W) float32
        Coverage in [0, 1]: 1 on the fragment for shading styles, the line/shadow strength for
        line and shadow styles (which may extend beyond the fragment mask).
    resolved : dict
        The values the style chose for its ``"auto"`` parameters (exposure, smoothing scale,
        gain, threshold, palette): drawing again with them gives the same picture, which is how
        tiles of a large image share one exposure.
    """

    rgb: np.ndarray
    alpha: np.ndarray
    resolved: dict = field(default_factory=dict)


def light_vector(azimuth_deg: float = 135.0, elevation_deg: float = 45.0) -> np.ndarray:
    """Unit light direction from azimuth (degrees counter-clockwise from +x, the image right) and
    elevation (degrees above the image plane); x right, y up, z towards the viewer.

    The default comes from the upper left, the convention of archaeological drawings; a raking
    light has an elevation of 5-20 degrees.
    """
    for name, value in (("azimuth_deg", azimuth_deg), ("elevation_deg", elevation_deg)):
        if not np.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
    if not -90.0 <= elevation_deg <= 90.0:
        raise ValueError(f"elevation_deg must be in [-90, 90], got {elevation_deg}")
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], np.float32)


def as_light(light) -> np.ndarray:
    """A light given as a 3-vector or as ``(azimuth_deg, elevation_deg)``, as a unit 3-vector.

    An (H, W, 3) array is a per-pixel light field of unit vectors (a light levelled to a
    surface's own plane, :func:`common.render.enhance.level_light`), returned as float32."""
    if isinstance(light, np.ndarray) and light.ndim == 3 and light.shape[2] == 3:
        return light.astype(np.float32, copy=False)
    arr = np.asarray(light, dtype=np.float64).ravel()
    if arr.size == 2:
        return light_vector(float(arr[0]), float(arr[1]))
    if arr.size != 3 or not np.all(np.isfinite(arr)) or np.linalg.norm(arr) == 0:
        raise ValueError(f"light must be a non-zero 3-vector or (azimuth_deg, elevation_deg), got {light!r}")
    return (arr / np.linalg.norm(arr)).astype(np.float32)


def dot_light(normals: np.ndarray, light: np.ndarray) -> np.ndarray:
    """n . l per pixel (float32); ``light`` a 3-vector or an (H, W, 3) light field."""
    if light.ndim == 3:
        return np.einsum("...i,...i->...", normals, light).astype(np.float32, copy=False)
    # one matrix-vector product (BLAS) instead of three strided products and their temporaries
    return np.asarray(normals, np.float32) @ np.asarray(light, np.float32)


def scale_colour(colour: np.ndarray, scale: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """``colour * scale[..., None]``, (H, W, 3) float32, for an (H, W, 3) colour and an (H, W)
    scale: OpenCV's product of interleaved channels (numpy's broadcast over a last axis of 3 is
    several times slower). ``out``: a contiguous (H, W, 3) float32 array to write to."""
    import cv2

    s = np.ascontiguousarray(scale, np.float32)
    return cv2.multiply(np.ascontiguousarray(colour, np.float32), cv2.merge([s, s, s]),
                        dst=np.empty(s.shape + (3,), np.float32) if out is None else out)


def smoothstep(edge0, edge1, x):
    """Hermite step 0 -> 1 between ``edge0`` and ``edge1`` (a hard step where they are equal)."""
    x = np.asarray(x, dtype=np.float32)
    if edge1 == edge0:
        return (x >= edge0).astype(np.float32)
    t = np.clip((x - edge0) / np.float32(edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def grey(value: np.ndarray) -> np.ndarray:
    """(H, W) -> (H, W, 3)."""
    import cv2

    v = np.ascontiguousarray(value, np.float32)
    return cv2.merge([v, v, v]).reshape(v.shape + (3,))   # one interleaving pass (np.repeat: three)


def display_albedo(albedo: np.ndarray) -> np.ndarray:
    """Linear albedo -> display (sRGB-encoded) colour: the colour a style paints with."""
    from common.rgbn.io import linear_to_srgb

    return linear_to_srgb(albedo)


def check_dpi(dpi) -> float:
    if not np.isfinite(dpi) or dpi <= 0:
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    return float(dpi)
