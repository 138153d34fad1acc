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
    shape = np.shape(u)
    u = np.atleast_2d(u.astype(np.float32))
    v = np.atleast_2d(v.astype(np.float32))
    return cv2.remap(tile, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).reshape(shape)


def affine_grid(G: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Wall coordinates (x_mm, y_mm), float32 (H, W), of a pixel grid with ``wall = G @ (col, row, 1)``."""
    H, W = shape
    cols = np.arange(W, dtype=np.float32)[None, :]
    rows = np.arange(H, dtype=np.float32)[:, None]
    G = np.asarray(G, np.float64)
    x = np.float32(G[0, 0]) * cols + np.float32(G[0, 1]) * rows + np.float32(G[0, 2])
    y = np.float32(G[1, 0]) * cols + np.float32(G[1, 1]) * rows + np.float32(G[1, 2])
    return x, y


def compose(T: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The 2x3 affine map ``T o G`` (apply G, then T)."""
    T, G = np.asarray(T, np.float64), np.asarray(G, np.float64)
    return np.hstack([T[:, :2] @ G[:, :2], (T[:, :2] @ G[:, 2] + T[:, 2])[:, None]])


def subgrid_factor(G: np.ndarray, scale_mm: float) -> int:
    """Power-of-two sub-sampling that still puts >= 8 samples per ``scale_mm`` on grid ``G``."""
    pixel_mm = float(np.sqrt(abs(np.linalg.det(np.asarray(G, float)[:, :2]))))
    k = 1
    while scale_mm / (pixel_mm * k * 2) >= 8.0 and k < 64:
        k *= 2
    return k


def on_subgrid(fn, G: np.ndarray, shape: tuple[int, int], k: int) -> np.ndarray:
    """Evaluate ``fn(G', shape')`` on a grid ``k`` times coarser and interpolate it up to ``shape``.

    Sample j of the sub-grid sits at full position (j - 0.5) k - 0.5 -- cv2.resize's convention,
    with one sample of margin on each side so that nothing is extrapolated.
    """
    if k <= 1:
        return fn(G, shape)
    sub_shape = (-(-shape[0] // k) + 2, -(-shape[1] // k) + 2)
    Gk = compose(G, [[k, 0, (k - 1) / 2.0 - k], [0, k, (k - 1) / 2.0 - k]])
    return upsample(fn(Gk, sub_shape), k, shape)


def sample_raster_grid(raster: np.ndarray, res_mm: float, G: np.ndarray, shape: tuple[int, int], *,
                       interpolation: int = cv2.INTER_LINEAR, border: int = cv2.BORDER_REPLICATE,
                       border_value: float = 0.0, smooth_mm: float | None = None) -> np.ndarray:
    """Sample a wall raster (pixel (r, c) at wall (c, r) * res_mm) on an affine pixel grid ``G``.

    One :func:`cv2.warpAffine` call: no coordinate arrays are built. With ``smooth_mm`` (the
    raster varies only over that scale) it is sampled on a coarser grid and interpolated.
    """
    if smooth_mm is not None:
        k = subgrid_factor(G, smooth_mm)
        if k > 1:
            return on_subgrid(lambda g, s: sample_raster_grid(raster, res_mm, g, s, interpolation=interpolation,
                                                              border=border, border_value=border_value),
                              G, shape, k)
    A = compose([[1.0 / res_mm, 0, 0], [0, 1.0 / res_mm, 0]], G)
    return cv2.warpAffine(raster, A, (int(shape[1]), int(shape[0])), flags=interpolation | cv2.WARP_INVERSE_MAP,
                          borderMode=border, borderValue=border_value)


def sample_tile_grid(tile: np.ndarray, G: np.ndarray, shape: tuple[int, int], *, px_per_mm: float,
                     angle_rad: float = 0.0, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """:func:`sample_tile` on an affine pixel grid ``wall = G @ (col, row, 1)`` (one warpAffine)."""
    c, s = np.cos(angle_rad) * px_per_mm, np.sin(angle_rad) * px_per_mm
    A = compose([[c, s, offset[0]], [-s, c, offset[1]]], G)
    A[:, 2] %= tile.shape[0]  # the tile is periodic: keep the coordinates small
    return cv2.warpAffine(tile, A, (int(shape[1]), int(shape[0])), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_WRAP)


def upsample(sub: np.ndarray, k: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear up-sampling of a sub-grid (sample j at full position (j - 0.5) k - 0.5) to ``shape``."""
    big = cv2.resize(sub, (sub.shape[1] * k, sub.shape[0] * k), interpolation=cv2.INTER_LINEAR)
    return big[k:k + shape[0], k:k + shape[1]]


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

    def grid(self, G: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """The field on an affine pixel grid ``wall = G @ (col, row, 1)``, (H, W) float32.

        Octaves much coarser than the pixel are evaluated on a sub-sampled grid and
        interpolated (bilinear) -- the same field, far fewer samples.
        """
        groups: dict[int, list] = {}
        for o in self.octaves:
            groups.setdefault(subgrid_factor(G, 4.0 / o["px_per_mm"]), []).append(o)
        out = np.zeros(shape, np.float32)
        for k, octs in groups.items():
            def octaves_on(g, s, octs=octs):
                acc = np.zeros(s, np.float32)
                for o in octs:
                    acc += np.float32(o["amp"]) * sample_tile_grid(self.tile, g, s, px_per_mm=o["px_per_mm"],
                                                                   angle_rad=o["angle_rad"], offset=o["offset"])
                return acc
            out += on_subgrid(octaves_on, G, shape, k)
        return out

    def __call__(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """The field at arbitrary wall points (mm)."""
        out = np.zeros(np.shape(x_mm), np.float32)
        for o in self.octaves:
            out += o["amp"] * sample_tile(self.tile, x_mm, y_mm, px_per_mm=o["px_per_mm"],
                                          angle_rad=o["angle_rad"], offset=o["offset"])
        return out
