"""Surface relief of a synthetic wall painting, laid over the whole wall before it breaks.

Layers (heights in mm, + out of the wall towards the viewer):

* undulation of the wall face (tenths of a mm over decimetres);
* string impressions: straight, shallow, rounded grooves where the painters snapped strings into
  the wet plaster to lay out bands (so mostly along colour boundaries);
* incisions: narrow V grooves along some outlines and spirals;
* brush strokes: parallel ridges whose orientation, frequency and depth vary by region (each
  region one working session of the plasterer/painter), blended smoothly between regions;
* plaster grain: fine isotropic roughness;
* thickness of the plaster (front face above the back), and the roughness of the back.

Because every layer is a function of the wall position, relief continues across true joins.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.synth.noise import (FractalField, periodic_noise_tile, sample_raster_grid, sample_tile,
                                sample_tile_grid)
from common.synth.painting import Painting

_STROKE_F0 = 16.0  # ridge frequency of the stroke tile, cycles per tile


def normals_from_height(height_mm: np.ndarray, pixel_mm: float) -> np.ndarray:
    """Unit surface normals of a height field, in the RGBN convention.

    ``n = (-dh/dx, -dh/dy_up, 1) / |.|`` with x to the right (columns) and y up (towards row 0),
    z towards the viewer; derivatives by central differences in mm.

    Parameters
    ----------
    height_mm : (H, W) array
        Height in mm, + towards the viewer.
    pixel_mm : float
        Pixel size in mm.

    Returns
    -------
    (H, W, 3) float32

    Examples
    --------
    >>> h = np.tile(np.arange(5.0), (4, 1))  # rises 1 mm per pixel to the right
    >>> np.round(normals_from_height(h, 1.0)[2, 2], 3)
    array([-0.707,  0.   ,  0.707], dtype=float32)
    """
    height_mm = np.asarray(height_mm, np.float32)
    if height_mm.ndim != 2:
        raise ValueError(f"height_mm must be 2-D, got shape {height_mm.shape}")
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be positive, got {pixel_mm}")
    d_row, d_col = np.gradient(height_mm, np.float32(pixel_mm))
    n = np.dstack([-d_col, d_row, np.ones_like(d_col)])  # d/dy_up = -d/drow
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return n.astype(np.float32)


@dataclass
class StrokeRegion:
    """One brush-stroke region: centre (mm), ridge orientation (rad, wall frame), period, depth."""

    x_mm: float
    y_mm: float
    angle_rad: float
    period_mm: float
    depth_mm: float


class WallRelief:
    """Relief and thickness of a whole wall, evaluated at any wall points.

    Parameters
    ----------
    painting : Painting
        Its string lines and incisions are pressed into the plaster; its size is the wall's.
    rng : numpy.random.Generator
    res_mm : float
        Pixel size of the raster holding undulation, strings and incisions.
    stroke_region_mm : float
        Typical size of a brush-stroke region.
    grain_mm, grain_depth_mm : float
        Correlation length and r.m.s. height of the plaster grain's coarser octave (both octaves together: about
        1.12 × ``grain_depth_mm``).
    thickness_mm : float
        Mean plaster thickness; it varies by about +-25 % over the wall.
    """

    def __init__(self, painting: Painting, rng: np.random.Generator, *, res_mm: float = 0.25,
                 stroke_region_mm: float = 90.0, grain_mm: float = 0.25, grain_depth_mm: float = 0.012,
                 thickness_mm: float = 20.0):
        if res_mm <= 0 or stroke_region_mm <= 0 or grain_mm <= 0 or thickness_mm <= 0:
            raise ValueError("res_mm, stroke_region_mm, grain_mm and thickness_mm must be positive")
        self.width_mm, self.height_mm = painting.size_mm
        self.res_mm = float(res_mm)
        W, H = int(np.ceil(self.width_mm / res_mm)), int(np.ceil(self.height_mm / res_mm))
        G = np.array([[res_mm, 0.0, 0.0], [0.0, res_mm, 0.0]])
        macro = FractalField(rng, 120.0, octaves=3, persistence=0.5, amplitude=0.25).grid(G, (H, W))
        macro += self._grooves(painting, rng, (H, W))
        self.macro = macro.astype(np.float32)
        self.grain = FractalField(rng, grain_mm, octaves=2, persistence=0.5, amplitude=grain_depth_mm)
        # brush-stroke regions on a jittered grid
        self.stroke_tile = periodic_noise_tile(rng, band=(_STROKE_F0, 0.3))
        nx = max(1, int(round(self.width_mm / stroke_region_mm)))
        ny = max(1, int(round(self.height_mm / stroke_region_mm)))
        self.regions: list[StrokeRegion] = []
        for j in range(ny):
            for i in range(nx):
                base = rng.choice([0.0, np.pi / 2, rng.uniform(0, np.pi)])  # plasterers work along/across
                self.regions.append(StrokeRegion(
                    x_mm=(i + rng.uniform(0.2, 0.8)) * self.width_mm / nx,
                    y_mm=(j + rng.uniform(0.2, 0.8)) * self.height_mm / ny,
                    angle_rad=float(base + rng.normal(0, 0.25)),
                    period_mm=float(np.exp(rng.uniform(np.log(0.6), np.log(3.0)))),
                    depth_mm=float(np.exp(rng.uniform(np.log(0.008), np.log(0.04))))))
        self._offsets = [(float(rng.uniform(0, 256)), float(rng.uniform(0, 256))) for _ in self.regions]
        # soft region weights on a coarse raster (2 mm): softmin of the distance to the centres
        self._w_res = 2.0
        gy, gx = np.mgrid[0:int(np.ceil(self.height_mm / 2)) + 1, 0:int(np.ceil(self.width_mm / 2)) + 1]
        gx, gy = gx * 2.0, gy * 2.0
        d = np.stack([np.hypot(gx - r.x_mm, gy - r.y_mm) for r in self.regions])
        tau = 0.12 * stroke_region_mm
        # cut off at 2 %: a region's strokes end a few cm beyond its border (exactly zero there,
        # so which regions a fragment sees does not depend on its bounding box)
        w = np.clip(np.exp(-(d - d.min(axis=0)) / tau) - 0.02, 0.0, None)
        self._weights = (w / w.sum(axis=0)).astype(np.float32)
        self.thickness_field = FractalField(rng, 150.0, octaves=3, persistence=0.5, amplitude=0.15 * thickness_mm)
        self.back_rough = FractalField(rng, 3.0, octaves=3, persistence=0.6, amplitude=0.4)
        self.thickness_mean = float(thickness_mm)

    def _grooves(self, painting: Painting, rng: np.random.Generator, shape) -> np.ndarray:
        """String impressions (rounded, shallow) and incisions (V-shaped, narrow) in mm."""
        k = 1.0 / self.res_mm
        out = np.zeros(shape, np.float32)
        # strings: each its own depth and width, Gaussian profile
        for (x0, y0), (x1, y1) in painting.string_lines:
            if rng.random() < 0.15:  # some strings were never snapped into the plaster
                continue
            lines = np.full(shape, 255, np.uint8)
            cv2.line(lines, (int(round(x0 * k * 16)), int(round(y0 * k * 16))),
                     (int(round(x1 * k * 16)), int(round(y1 * k * 16))), 0, 1, cv2.LINE_8, shift=4)
            dist = cv2.distanceTransform(lines, cv2.DIST_L2, 5) * self.res_mm
            depth, width = rng.uniform(0.08, 0.25), rng.uniform(0.4, 0.9)
            out -= depth * np.exp(-0.5 * (dist / (0.5 * width)) ** 2)
        if painting.incisions:
            lines = np.full(shape, 255, np.uint8)
            for pts in painting.incisions:
                p = np.round(np.asarray(pts) * k * 16).astype(np.int32).reshape(-1, 1, 2)
                cv2.polylines(lines, [p], False, 0, 1, cv2.LINE_8, shift=4)
            dist = cv2.distanceTransform(lines, cv2.DIST_L2, 5) * self.res_mm
            half = 0.35
            out -= 0.25 * np.clip(1.0 - dist / half, 0.0, None)
        return out

    # -- evaluation ------------------------------------------------------------------------
    def strokes(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Brush-stroke relief (mm) at wall points."""
        x_mm = np.asarray(x_mm, np.float32)
        y_mm = np.asarray(y_mm, np.float32)
        u, v = x_mm / self._w_res, y_mm / self._w_res
        out = np.zeros(x_mm.shape, np.float32)
        # only regions with weight somewhere near these points
        ci = np.clip(np.round(u.ravel()).astype(int), 0, self._weights.shape[2] - 1)
        ri = np.clip(np.round(v.ravel()).astype(int), 0, self._weights.shape[1] - 1)
        active = np.nonzero(self._weights[:, ri, ci].reshape(len(self.regions), -1).max(axis=1) > 0)[0]
        for k in active:
            reg = self.regions[k]
            w = cv2.remap(self._weights[k], np.atleast_2d(u), np.atleast_2d(v), cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE).reshape(u.shape)
            # the tile's ridges run along its x axis; ridge period = tile period / F0
            s = sample_tile(self.stroke_tile, x_mm, y_mm, px_per_mm=(256.0 / _STROKE_F0) / reg.period_mm,
                            angle_rad=reg.angle_rad, offset=self._offsets[k])
            out += w * reg.depth_mm * s
        return out

    def strokes_grid(self, G: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """:meth:`strokes` on an affine pixel grid ``wall = G @ (col, row, 1)``."""
        out = np.zeros(shape, np.float32)
        H, W = shape
        corners = np.array([[0, 0, 1], [W - 1, 0, 1], [0, H - 1, 1], [W - 1, H - 1, 1]], float) @ np.asarray(G).T
        (x0, y0), (x1, y1) = corners.min(axis=0), corners.max(axis=0)
        wr = self._weights[:, max(int(y0 / self._w_res) - 1, 0):int(y1 / self._w_res) + 2,
                           max(int(x0 / self._w_res) - 1, 0):int(x1 / self._w_res) + 2]
        if wr.size == 0:
            wr = self._weights
        active = np.nonzero(wr.reshape(len(self.regions), -1).max(axis=1) > 0)[0]
        for k in active:
            reg = self.regions[k]
            w = sample_raster_grid(self._weights[k], self._w_res, G, shape, smooth_mm=4 * self._w_res)
            s = sample_tile_grid(self.stroke_tile, G, shape, px_per_mm=(256.0 / _STROKE_F0) / reg.period_mm,
                                 angle_rad=reg.angle_rad, offset=self._offsets[k])
            out += w * np.float32(reg.depth_mm) * s
        return out

    def height_grid(self, G: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """:meth:`height` on an affine pixel grid ``wall = G @ (col, row, 1)``."""
        h = sample_raster_grid(self.macro, self.res_mm, G, shape, interpolation=cv2.INTER_CUBIC)
        h += self.strokes_grid(G, shape)
        h += self.grain.grid(G, shape)
        return h

    def thickness_grid(self, G: np.ndarray, shape: tuple[int, int], *,
                       back_rough: np.ndarray | None = None) -> np.ndarray:
        """:meth:`thickness` on an affine pixel grid (``back_rough``: that field on the grid, if at hand)."""
        if back_rough is None:
            back_rough = self.back_rough.grid(G, shape)
        t = self.thickness_mean + self.thickness_field.grid(G, shape) - back_rough
        return np.maximum(t, 0.2 * self.thickness_mean)

    def height(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Front-face relief height (mm) at wall points: macro + strokes + grain."""
        x_mm = np.asarray(x_mm, np.float32)
        y_mm = np.asarray(y_mm, np.float32)
        h = cv2.remap(self.macro, np.atleast_2d(x_mm / np.float32(self.res_mm)),
                      np.atleast_2d(y_mm / np.float32(self.res_mm)), cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REPLICATE).reshape(x_mm.shape)
        h += self.strokes(x_mm, y_mm)
        h += self.grain(x_mm, y_mm)
        return h

    def thickness(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Plaster thickness (mm) at wall points: front face above the rough back."""
        t = self.thickness_mean + self.thickness_field(x_mm, y_mm) - self.back_rough(x_mm, y_mm)
        return np.maximum(t, 0.2 * self.thickness_mean)
