"""Smooth random fields defined on the wall plane, evaluated at any points.

Every layer of the synthetic fresco (crack jaggedness, plaster grain, brush strokes, thickness)
is a function of the wall position in millimetres, never of a fragment's pixel grid. Two
fragments that shared a crack therefore see the same values on both sides of it, whatever their
rotation and sampling. A field is a periodic noise tile (spectrally shaped white noise, so it
wraps without seams) sampled with :func:`cv2.remap` at rotated, scaled coordinates; fractal
fields sum several such octaves with independent rotations and offsets, which hides the tile
period.
"""

from __future__ import annotations

import cv2
import numpy as np

_TILE = 256


def periodic_noise_tile(rng: np.random.Generator, size: int = _TILE, *, corr_px: float = 4.0,
                        band: tuple[float, float] | None = None) -> np.ndarray:
    """A seamless (periodic) random tile with zero mean and unit standard deviation.

    Parameters
    ----------
    rng : numpy.random.Generator
    size : int
        Tile side in pixels.
    corr_px : float
        Gaussian correlation length in tile pixels (isotropic tiles).
    band : (f0, bandwidth) or None
        Instead of isotropic noise, stripes running along x with dominant spatial frequency ``f0``
        cycles per tile across them (along y) and relative bandwidth ``bandwidth``: the texture
        of parallel brush strokes.

    Returns
    -------
    (size, size) float32
    """
    if size < 8:
        raise ValueError(f"size must be at least 8 pixels, got {size}")
    white = rng.standard_normal((size, size))
    fy = np.fft.fftfreq(size)[:, None] * size  # cycles per tile
    fx = np.fft.fftfreq(size)[None, :] * size
    if band is None:
        # Gaussian low-pass: correlation length corr_px px <=> sigma_f = size / (2 pi corr_px)
        sig = size / (2 * np.pi * max(corr_px, 0.5))
        gain = np.exp(-0.5 * (fx ** 2 + fy ** 2) / sig ** 2)
    else:
        f0, bw = band
        # ridge spectrum: narrow along x (long strokes), peaked at +-f0 across
        gain = (np.exp(-0.5 * ((np.abs(fy) - f0) / (bw * f0)) ** 2)
                * np.exp(-0.5 * (fx / max(f0 / 10.0, 0.6)) ** 2))
    tile = np.real(np.fft.ifft2(np.fft.fft2(white) * gain))
    tile -= tile.mean()
    tile /= tile.std() + 1e-12
    return tile.astype(np.float32)


def sample_tile(tile: np.ndarray, x_mm: np.ndarray, y_mm: np.ndarray, *, px_per_mm: float,
                angle_rad: float = 0.0, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Sample a periodic tile at wall points (mm), rotated by ``angle_rad`` and scaled.

    The tile's x axis points along ``angle_rad`` on the wall (x right, y down).
    """
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    n = tile.shape[0]
    u = ((c * x_mm + s * y_mm) * px_per_mm + offset[0]) % n
    v = ((-s * x_mm + c * y_mm) * px_per_mm + offset[1]) % n
    return cv2.remap(tile, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_WRAP)


class FractalField:
    """Sum of noise octaves: a stationary random field f(x_mm, y_mm) on the wall.

    Parameters
    ----------
    rng : numpy.random.Generator
    scale_mm : float
        Correlation length of the coarsest octave.
    octaves : int
        Number of octaves; each halves the scale.
    persistence : float
        Amplitude ratio between successive octaves (0.5 = amplitude proportional to scale,
        larger = rougher, more jagged).
    amplitude : float
        Standard deviation of the coarsest octave (output units).
    """

    def __init__(self, rng: np.random.Generator, scale_mm: float, *, octaves: int = 1,
                 persistence: float = 0.5, amplitude: float = 1.0, tile: np.ndarray | None = None):
        if scale_mm <= 0:
            raise ValueError(f"scale_mm must be positive, got {scale_mm}")
        if octaves < 1:
            raise ValueError(f"octaves must be >= 1, got {octaves}")
        self.tile = periodic_noise_tile(rng) if tile is None else tile
        corr_px = 4.0  # correlation length of the tile in its own pixels
        self.octaves = []
        for k in range(octaves):
            scale = scale_mm / 2 ** k
            self.octaves.append(dict(px_per_mm=corr_px / scale, angle_rad=float(rng.uniform(0, 2 * np.pi)),
                                     offset=(float(rng.uniform(0, _TILE)), float(rng.uniform(0, _TILE))),
                                     amp=amplitude * persistence ** k))

    def __call__(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        out = np.zeros(np.shape(x_mm), np.float32)
        for o in self.octaves:
            out += o["amp"] * sample_tile(self.tile, x_mm, y_mm, px_per_mm=o["px_per_mm"],
                                          angle_rad=o["angle_rad"], offset=o["offset"])
        return out
