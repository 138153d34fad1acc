"""Colour descriptors: mean per channel, variance, saturation (§5.4.1).

Every statistic here is a function of weighted means of a few per-pixel channels (the *moments*),
so the same formula serves a whole fragment and a patch: the extractor area-averages the moment
channels once and sums them under each patch disc, which gives the full-resolution statistic
without revisiting every pixel.
"""

from __future__ import annotations

import numpy as np

#: per-pixel moment channels the colour descriptors need
COLOUR_MOMENTS = ("r", "g", "b", "rr", "gg", "bb", "sat")


def colour_channels(albedo, centre=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
    """Per-pixel moment channels of an (H, W, 3) linear RGB albedo (float32).

    The channels are centred on ``centre`` (e.g. the fragment's mean colour) so that variances
    summed in float32 do not cancel; :func:`colour_from_moments` adds it back.
    """
    a = np.asarray(albedo, dtype=np.float32)
    mx = np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])
    mn = np.minimum(np.minimum(a[..., 0], a[..., 1]), a[..., 2])
    sat = np.where(mx > 1e-6, (mx - mn) / np.maximum(mx, 1e-6), 0.0).astype(np.float32)
    r, g, b = (a[..., k] - np.float32(centre[k]) for k in range(3))
    return {"r": r, "g": g, "b": b, "rr": r * r, "gg": g * g, "bb": b * b, "sat": sat}


def colour_from_moments(m, centre=(0.0, 0.0, 0.0)) -> dict[str, float]:
    """Colour descriptors from weighted means of :data:`COLOUR_MOMENTS` (dict name -> mean) of
    channels centred on ``centre``."""
    var = sum(max(m[c + c] - m[c] ** 2, 0.0) for c in "rgb")
    return {"colour_mean_r": float(m["r"] + centre[0]), "colour_mean_g": float(m["g"] + centre[1]),
            "colour_mean_b": float(m["b"] + centre[2]),
            "colour_variance": float(var), "saturation": float(m["sat"])}


def colour_statistics(albedo, mask) -> dict[str, float]:
    """Colour mean per channel, colour variance and mean saturation of a fragment region.

    Parameters
    ----------
    albedo : (H, W, 3) float
        Linear RGB albedo in [0, 1].
    mask : (H, W) bool or float
        Region (or per-pixel weights in [0, 1]).

    Returns
    -------
    dict
        ``colour_mean_r/g/b`` (mean albedo), ``colour_variance`` (sum of the three channel
        variances) and ``saturation`` (mean HSV saturation (max − min) / max); NaN for an empty
        region.

    References
    ----------
    Toler-Franklin 2011, §5.4.1 (colour features).

    Examples
    --------
    >>> s = colour_statistics(np.full((4, 4, 3), [0.5, 0.25, 0.25]), np.ones((4, 4), bool))
    >>> s["colour_variance"], s["saturation"]
    (0.0, 0.5)
    """
    a = np.asarray(albedo, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"albedo must be (H, W, 3), got {a.shape}")
    w = np.asarray(mask, dtype=np.float32)
    if w.shape != a.shape[:2]:
        raise ValueError(f"mask must be {a.shape[:2]}, got {w.shape}")
    tot = float(w.sum())
    if tot <= 0:
        return {k: float("nan") for k in colour_from_moments({c: 0.0 for c in COLOUR_MOMENTS})}
    centre = tuple(float(np.sum(a[..., k] * w, dtype=np.float64)) / tot for k in range(3))
    ch = colour_channels(a, centre)  # centred: float32 squares do not cancel
    return colour_from_moments({k: float(np.sum(v * w, dtype=np.float64)) / tot for k, v in ch.items()}, centre)
