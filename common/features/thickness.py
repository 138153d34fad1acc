"""Thickness (§5.4.7): the mean of a height or thickness map where one exists."""

from __future__ import annotations

import numpy as np


def mean_thickness(height_mm, mask) -> float:
    """Mean of ``height_mm`` over the finite values inside ``mask``.

    Parameters
    ----------
    height_mm : (H, W) float or None
        Height/thickness map in mm (NaN where unknown); None when the face has none.
    mask : (H, W) bool or float
        Region (or weights in [0, 1]).

    Returns
    -------
    float
        Weighted mean in mm; NaN without a map or without a finite value in the region.

    References
    ----------
    Toler-Franklin 2011, §5.4.7 (3-D features: thickness).

    Examples
    --------
    >>> mean_thickness(np.full((4, 4), 12.5), np.ones((4, 4), bool))
    12.5
    >>> mean_thickness(None, np.ones((4, 4), bool))
    nan
    """
    if height_mm is None:
        return float("nan")
    h = np.asarray(height_mm, dtype=np.float64)
    w = np.asarray(mask, dtype=np.float64)
    if h.shape != w.shape:
        raise ValueError(f"height_mm {h.shape} and mask {w.shape} must have the same shape")
    ok = np.isfinite(h)
    tot = float(np.sum(w[ok]))
    return float(np.sum(h[ok] * w[ok]) / tot) if tot > 0 else float("nan")
