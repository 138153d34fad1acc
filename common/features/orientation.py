"""Dominant orientation of the surface relief: brush strokes, string impressions (§5.4.5, eq. 5.4).

The smoothed normal-z map of a region is windowed with a Hanning window and Fourier transformed;
the strongest peak at least ω_min = 3 cycles per window from the origin gives the dominant
frequency, its amplitude, and the direction of its wave vector. Per patch that direction is
reported relative to the outward contour normal (eq. 5.4), which makes it invariant to how the
fragment lay on the scanner and comparable across a join: the neighbour's contour normal is
opposite, and the angle is axial (modulo 180°).
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft
from scipy import ndimage as ndi

#: lowest frequency considered, cycles per window (§5.4.5)
OMEGA_MIN = 3.0


def dominant_orientation(nz, mask, pixel_mm, *, omega_min=OMEGA_MIN, smooth_px=1.0,
                         reference_normal=None, pad=1.5):
    """Frequency, amplitude and angle of the strongest periodic relief in a region (eq. 5.4).

    Parameters
    ----------
    nz : (H, W) float
        z component of the unit normals of a window around the region.
    mask : (H, W) bool
        Region pixels; the others are filled with the region's mean so the region's outline
        does not dominate the spectrum.
    pixel_mm : float
        Pixel size, mm.
    omega_min : float
        Lowest frequency considered, in cycles per window (ω_min = 3 in the thesis).
    smooth_px : float
        Gaussian smoothing of nz before the transform, pixels (0 = none).
    reference_normal : (2,) float, optional
        Outward contour normal (x right, y down). If given, the returned angle is relative to it.
    pad : float
        Zero-padding factor of the FFT (finer frequency sampling of the peak).

    Returns
    -------
    dict
        ``orient_frequency`` (cycles/mm), ``orient_amplitude`` (peak amplitude in nz units) and
        ``orient_angle`` (degrees in [0, 180): direction of the wave vector, i.e. across the
        strokes, in the fragment frame x right / y down, relative to ``reference_normal`` when
        given). NaN when fewer than a quarter of the window's pixels are in the region.

    References
    ----------
    Toler-Franklin 2011, §5.4.5, eq. 5.4; Toler-Franklin et al., "Multi-feature matching of
    fresco fragments", SIGGRAPH Asia 2010.

    Examples
    --------
    >>> yy, xx = np.mgrid[:64, :64]
    >>> nz = 0.9 + 0.05 * np.cos(2 * np.pi * xx / 8.0)
    >>> d = dominant_orientation(nz, np.ones((64, 64), bool), 0.1, smooth_px=0)
    >>> round(d["orient_frequency"], 2), round(d["orient_angle"]) % 180
    (1.25, 0)
    """
    z = np.asarray(nz, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if z.ndim != 2:
        raise ValueError(f"nz must be 2-D, got shape {z.shape}")
    if m.shape != z.shape:
        raise ValueError(f"mask must be {z.shape}, got {m.shape}")
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be positive, got {pixel_mm}")
    if not omega_min >= 0:
        raise ValueError(f"omega_min must be >= 0, got {omega_min}")
    nan = {"orient_frequency": np.nan, "orient_amplitude": np.nan, "orient_angle": np.nan}
    h, w = z.shape
    if h < 4 or w < 4 or m.sum() < 0.25 * h * w:
        return nan
    mean = float(z[m].mean())
    z = np.where(m, z, mean)
    if smooth_px > 0:
        z = ndi.gaussian_filter(z, smooth_px, mode="nearest")
    win = np.outer(np.hanning(h), np.hanning(w))
    z = (z - mean) * win
    n = sfft.next_fast_len(int(np.ceil(max(h, w) * max(pad, 1.0))), real=True)
    spec = np.abs(sfft.rfft2(z, s=(n, n)))
    fy = np.fft.fftfreq(n)[:, None]          # cycles per pixel along rows (y down)
    fx = np.fft.rfftfreq(n)[None, :]         # cycles per pixel along columns (x right)
    omega = np.sqrt((fy * h) ** 2 + (fx * w) ** 2)  # cycles per window
    spec = np.where(omega >= omega_min, spec, 0.0)
    i, j = np.unravel_index(int(np.argmax(spec)), spec.shape)
    if spec[i, j] <= 0:
        return nan
    vy, vx = float(fy[i, 0]), float(fx[0, j])
    angle = np.degrees(np.arctan2(vy, vx))
    if reference_normal is not None:
        angle -= np.degrees(np.arctan2(reference_normal[1], reference_normal[0]))
    return {"orient_frequency": float(np.hypot(vx, vy) / pixel_mm),
            "orient_amplitude": float(2.0 * spec[i, j] / win.sum()),
            "orient_angle": float(np.mod(angle, 180.0))}
