"""A physically based simulated flatbed scanner (thesis §3.3.2–3.3.3).

The simulated scanner images a :class:`~common.acquisition.surface.FragmentSurface` lying face
down on the glass the way a CCD flatbed does: the sensor line looks straight up (orthographic),
and a linear lamp parallel to the sensor line, offset by ``offset_mm`` along the travel direction
and ``height_mm`` below the glass, moves with it. Every surface point therefore sees the same
lamp geometry; its irradiance is the lamp's light integrated over the lamp's length onto a
Lambertian surface (:func:`lamp_irradiance`), plus a weak isotropic term from the optical
chamber, attenuated where the ray to a lamp sample is blocked by the fragment (the lamp's shadow
beside the fragment edges and in deep relief). The sensor adds shot and read noise and quantises
to 8 or 16 bits. The operator's hands are simulated too: :meth:`SimulatedFlatbed.rotate` turns
the fragment by the requested angle ±10° and nudges it, :meth:`SimulatedFlatbed.flip` shows the
other face.

Frames
------
Bed coordinates are millimetres, x along the sensor line (image columns, to the right), y along
the travel (image rows, downwards), origin at the top-left corner of the glass. Scan areas are
``(left, top, right, bottom)`` in bed mm; the pixel (row i, col j) of a scan at ``dpi`` has its
centre at ``(left + (j + 0.5) p, top + (i + 0.5) p)`` with ``p = 25.4 / dpi``. A fragment pose
``(angle_deg, tx_mm, ty_mm)`` maps fragment-frame mm ``q`` (x = col × pixel_mm, y = row × pixel_mm)
to bed mm by ``R(angle) q + t``, ``R = [[cos, -sin], [sin, cos]]`` (clockwise on the image).
The surface arrays are rendered as the sensor sees them (no mirroring), and normals follow the
RGBN convention (x right, y up, z towards the sensor).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage

from common.acquisition.errors import ScannerError
from common.acquisition.surface import FragmentSurface
from common.rgbn.image import RGBNImage


@dataclass(frozen=True)
class LampGeometry:
    """Geometry and photometry of the scanner's linear lamp.

    Attributes
    ----------
    offset_mm : float
        Lamp line offset from the sensor line along the travel; positive = towards image row 0,
        so the light comes from the top of the image (+y in the normal convention).
    height_mm : float
        Lamp line distance below the glass.
    half_angle_deg : float
        Half the angle the lamp spans as seen from a surface point (a lamp much longer than the
        fragment spans nearly ±90°; light beyond this angle is negligible).
    nodes : int
        Gauss–Legendre nodes of the quadrature over the lamp's length.
    ambient : float
        Isotropic light from the optical chamber, relative to the lamp's direct light on a flat
        surface at the glass.
    """

    offset_mm: float = 12.0
    height_mm: float = 12.0
    half_angle_deg: float = 80.0
    nodes: int = 8
    ambient: float = 0.08


def _lamp_nodes(lamp: LampGeometry) -> tuple[np.ndarray, np.ndarray]:
    xi, w = np.polynomial.legendre.leggauss(lamp.nodes)
    half = np.deg2rad(lamp.half_angle_deg)
    return xi * half, w * half


def lamp_irradiance(normals: np.ndarray, depth_mm: np.ndarray | float, lamp: LampGeometry = LampGeometry(),
                    visibility: np.ndarray | None = None) -> np.ndarray:
    """Irradiance of a Lambertian surface under the flatbed's linear lamp (§3.3.2).

    The lamp is the line ``{(u, d, D) : u in R}`` relative to the surface point, ``d`` the lamp's
    offset and ``D = height + depth`` its distance below the point. With ``L = (u, d, D)`` the
    irradiance is ``E = ∫ max(0, n·L) / |L|^3 du``; substituting ``u = r tan α`` with
    ``r = sqrt(d² + D²)`` gives the smooth integrand
    ``E = ∫ max(0, n_x sin α + (n_y d + n_z D) cos α / r) / r dα``, evaluated by Gauss–Legendre
    quadrature over ``|α| ≤ half_angle``. An isotropic ambient term ``ambient (1 + n_z) / 2`` is
    added. Normalised so that a flat surface (n = z) at the glass, fully visible, gets 1.

    Parameters
    ----------
    normals : (..., 3) array
        Unit normals, x right, y up (towards the lamp side), z towards the sensor.
    depth_mm : (...) array or float
        Distance of the surface point behind the glass, mm (>= 0).
    lamp : LampGeometry
    visibility : (K, ...) array or None
        Fraction of each lamp node visible from each point (shadows); None = all visible.

    Returns
    -------
    (...) float32 array
    """
    normals = np.asarray(normals, dtype=np.float32)
    if normals.shape[-1] != 3:
        raise ValueError(f"normals must have a last axis of 3, got {normals.shape}")
    alpha, weight = _lamp_nodes(lamp)
    D = np.float32(lamp.height_mm) + np.asarray(depth_mm, dtype=np.float32)
    d = np.float32(lamp.offset_mm)
    r = np.sqrt(d * d + D * D)
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    along = (ny * d + nz * D) / r
    total = np.zeros(np.broadcast_shapes(nx.shape, np.shape(D)), np.float32)
    for k, (a, w) in enumerate(zip(alpha, weight)):
        term = np.maximum(nx * np.float32(np.sin(a)) + along * np.float32(np.cos(a)), 0.0)
        if visibility is not None:
            term = term * visibility[k]
        total += np.float32(w) * term
    total /= r
    # reference: flat, at the glass, fully visible
    r0 = np.hypot(lamp.offset_mm, lamp.height_mm)
    ref = float(np.sum(weight * np.cos(alpha))) * lamp.height_mm / r0 / r0 + lamp.ambient
    return ((total + np.float32(lamp.ambient) * (1.0 + nz) / 2.0) / np.float32(ref)).astype(np.float32)


def _shadow_visibility(depth_mm: np.ndarray, solid: np.ndarray, pixel_mm: float, lamp: LampGeometry,
                       lid_mm: float, max_len_mm: float = np.inf) -> np.ndarray:
    """Per lamp node, 1 where a point sees the node, 0 where the fragment blocks the ray.

    The fragment is a solid from its face (``depth_mm``) back to the lid (``lid_mm``) wherever
    ``solid``; the ray from a point towards a lamp node rises towards the glass with slope
    ``D / |(u, d)|`` and is blocked if it passes through that solid. Marched in whole pixels on
    the (coarse) grid given.
    """
    alpha, _ = _lamp_nodes(lamp)
    D0 = lamp.height_mm + lid_mm / 2.0
    r = np.hypot(lamp.offset_mm, D0)
    H, W = depth_mm.shape
    blocker = np.where(solid, depth_mm, np.inf).astype(np.float32)
    vis = np.ones((len(alpha), H, W), np.float32)
    for k, a in enumerate(alpha):
        u = r * np.tan(a)
        horiz = np.hypot(u, lamp.offset_mm)
        slope = D0 / horiz                        # depth climbed per mm travelled towards the lamp
        dcol, drow = u / horiz, -lamp.offset_mm / horiz   # lamp side is image-up (row decreasing)
        max_steps = int(np.ceil(min(lid_mm / slope, max_len_mm) / pixel_mm)) + 1
        blocked = np.zeros((H, W), bool)
        for s in range(1, max_steps + 1):
            oc, orow = int(round(s * dcol)), int(round(s * drow))
            if abs(oc) >= W or abs(orow) >= H:
                break
            shifted = np.full((H, W), np.inf, np.float32)
            # shifted[i, j] = blocker[i + orow, j + oc]
            src = blocker[max(orow, 0):H + min(orow, 0), max(oc, 0):W + min(oc, 0)]
            shifted[max(-orow, 0):H + min(-orow, 0), max(-oc, 0):W + min(-oc, 0)] = src
            blocked |= shifted < depth_mm - s * pixel_mm * slope
        vis[k] = ~blocked
    return vis


def _fill_outside(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Copy each outside pixel from its nearest inside pixel (so resampling at the edge is sane)."""
    if mask.all() or not mask.any():
        return values
    idx = ndimage.distance_transform_edt(~mask, return_distances=False, return_indices=True)
    return values[tuple(idx)]


@dataclass
class _Placed:
    surface: FragmentSurface
    angle_deg: float
    centre_mm: np.ndarray           # bed position of the surface's centre


@dataclass
class ScanRecord:
    """What the simulator did for one scan (ground truth for tests and benchmarks)."""

    area_mm: tuple
    dpi: float
    poses: list                     # (angle_deg, tx_mm, ty_mm) per object on the bed
    faces: list


def plain_back(front: FragmentSurface, seed: int = 0) -> FragmentSurface:
    """A rough, plain plaster back face for a surface that has none (mirror of the footprint)."""
    rng = np.random.default_rng(seed)
    mask = front.mask[:, ::-1].copy()
    h, w = mask.shape
    rough = ndimage.gaussian_filter(rng.normal(size=(h, w)), 4.0)
    rough = (rough / (rough.std() + 1e-9) * 0.15).astype(np.float32)
    albedo = np.empty((h, w, 3), np.float32)
    albedo[:] = np.array([0.62, 0.58, 0.52], np.float32)
    albedo *= (1 + 0.3 * rough[..., None])
    return FragmentSurface(albedo=np.clip(albedo, 0, 1), height_mm=rough, mask=mask, dpi=front.dpi,
                           thickness_mm=front.thickness_mm, back=front)


class SimulatedFlatbed:
    """A simulated flatbed with a linear lamp, a textured lid, dust on the glass and sensor noise.

    Parameters
    ----------
    name : str
        Device name (stored with each scan; calibrations are per device name).
    bed_mm : (width, height)
        Glass size in mm (A4: 216 × 297).
    lamp : LampGeometry
    noise : float
        Shot-noise scale: standard deviation relative to full scale of a full-scale signal
        (variance = noise² · signal + read_noise²).
    read_noise : float
        Signal-independent noise, relative to full scale.
    exposure : float
        Sensor reading of a white (albedo 1) flat surface at the glass, relative to full scale.
    lid_albedo : float
        Mean reflectance of the (dark) lid that forms the background.
    dust : int
        Number of dust specks on the glass.
    seed : int
        Seed of the simulator's random state (lid texture, dust, noise, operator's hands).
    """

    def __init__(self, name: str = "sim", *, bed_mm=(216.0, 297.0), lamp: LampGeometry = LampGeometry(),
                 noise: float = 0.003, read_noise: float = 0.0005, exposure: float = 0.75,
                 lid_albedo: float = 0.06, dust: int = 40, seed: int = 0):
        if noise < 0 or read_noise < 0:
            raise ValueError("noise and read_noise must be >= 0")
        self.name = name
        self.bed_mm = (float(bed_mm[0]), float(bed_mm[1]))
        self.lamp = lamp
        self.noise = float(noise)
        self.read_noise = float(read_noise)
        self.exposure = float(exposure)
        self.lid_albedo = float(lid_albedo)
        self.rng = np.random.default_rng(seed)
        rng = np.random.default_rng(seed + 1)
        # lid texture on a 2 mm grid, smooth, fixed in bed coordinates
        tex = ndimage.gaussian_filter(rng.normal(size=(int(self.bed_mm[1] / 2) + 2, int(self.bed_mm[0] / 2) + 2)), 1.5)
        self._lid_tex = (tex / (tex.std() + 1e-9) * 0.25).astype(np.float32)
        self._dust = np.column_stack([rng.uniform(0, self.bed_mm[0], dust), rng.uniform(0, self.bed_mm[1], dust),
                                      rng.uniform(0.05, 0.25, dust)])            # x, y, radius mm
        self._items: list[_Placed] = []
        self.history: list[ScanRecord] = []
        self.fault: str | None = None      # set to a SANE-like status to simulate a failing device

    # -- the operator's side --------------------------------------------------------------
    def place(self, surface: FragmentSurface, *, angle_deg: float | None = None, centre_mm=None) -> None:
        """Put a fragment on the (cleared) glass at a random or given pose."""
        self._items = []
        self.add(surface, angle_deg=angle_deg, centre_mm=centre_mm)

    def add(self, surface: FragmentSurface, *, angle_deg: float | None = None, centre_mm=None) -> None:
        """Put one more object on the glass (e.g. to test the multiple-fragments error)."""
        if not isinstance(surface, FragmentSurface):
            raise ValueError(f"surface must be a FragmentSurface, got {type(surface).__name__}")
        radius = self._radius_mm(surface)
        if centre_mm is None:
            lo = np.array([radius + 10, radius + 10])
            hi = np.array(self.bed_mm) - lo
            if np.any(hi <= lo):
                raise ValueError("surface is larger than the scanner bed")
            centre_mm = self.rng.uniform(lo, hi)
        if angle_deg is None:
            angle_deg = float(self.rng.uniform(0, 360))
        self._items.append(_Placed(surface, float(angle_deg), np.asarray(centre_mm, float)))

    def clear(self) -> None:
        """Take everything off the glass."""
        self._items = []

    def rotate(self, deg: float = 90.0, *, error_deg: float = 10.0, shift_mm: float = 2.0) -> None:
        """Turn the fragment by ``deg`` clockwise (on the image) as a person would: ±error, nudged."""
        for it in self._items:
            it.angle_deg += deg + float(self.rng.uniform(-error_deg, error_deg))
            it.centre_mm = it.centre_mm + self.rng.normal(0, shift_mm, 2)
            it.centre_mm = np.clip(it.centre_mm, self._radius_mm(it.surface) + 2,
                                   np.array(self.bed_mm) - self._radius_mm(it.surface) - 2)

    def flip(self) -> None:
        """Turn the fragment over: the other face lies on the glass (a plain back if it has none)."""
        for it in self._items:
            back = it.surface.back if it.surface.back is not None else plain_back(it.surface)
            if back.back is None:
                back = replace(back, back=it.surface)
            it.surface = back

    # -- the scanner interface ------------------------------------------------------------
    def scan(self, area_mm=None, dpi: float = 600, depth: int = 16) -> np.ndarray:
        """Scan ``area_mm`` = (left, top, right, bottom) of the bed (None = the whole bed).

        Returns (H, W, 3) uint16 (depth 16) or uint8 (depth 8), linear sensor values.
        """
        if self.fault:
            raise ScannerError(f"simulated device fault {self.fault}", status=self.fault)
        img, _ = self._render(area_mm, dpi, depth=depth, with_truth=False)
        return img

    def truth(self, area_mm=None, dpi: float = 600) -> RGBNImage:
        """Noise-free ground truth (albedo, normals, mask) of the current placement in a scan's frame."""
        _, truth = self._render(area_mm, dpi, depth=None, with_truth=True)
        return truth

    # -- rendering --------------------------------------------------------------------------
    @staticmethod
    def _radius_mm(surface: FragmentSurface) -> float:
        h, w = surface.mask.shape
        return 0.5 * np.hypot(h, w) * surface.pixel_mm

    def _area(self, area_mm, dpi):
        if dpi is None or not dpi > 0:
            raise ValueError(f"dpi must be positive, got {dpi}")
        if area_mm is None:
            area_mm = (0.0, 0.0) + self.bed_mm
        x0, y0, x1, y1 = (float(v) for v in area_mm)
        if not (0 <= x0 < x1 <= self.bed_mm[0] + 1e-6 and 0 <= y0 < y1 <= self.bed_mm[1] + 1e-6):
            raise ValueError(f"area_mm {area_mm} must lie inside the bed 0..{self.bed_mm[0]} × 0..{self.bed_mm[1]} mm")
        return (x0, y0, x1, y1)

    def _face_maps(self, xs, ys, pix):
        """Resample every placed face onto bed points (xs, ys): albedo, height, mask, object index."""
        H, W = xs.shape
        albedo = np.zeros((H, W, 3), np.float32)
        height = np.zeros((H, W), np.float32)
        inside = np.zeros((H, W), bool)
        for it in self._items:
            s = it.surface
            h, w = s.mask.shape
            c, sn = np.cos(np.deg2rad(it.angle_deg)), np.sin(np.deg2rad(it.angle_deg))
            centre_q = np.array([(w - 1) / 2, (h - 1) / 2]) * s.pixel_mm
            t = it.centre_mm - np.array([[c, -sn], [sn, c]]) @ centre_q
            dx, dy = xs - t[0], ys - t[1]
            qx = (c * dx + sn * dy) / s.pixel_mm      # R^T (bed - t), in surface pixels
            qy = (-sn * dx + c * dy) / s.pixel_mm
            mx, my = qx.astype(np.float32), qy.astype(np.float32)
            m = cv2.remap(s.mask.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderValue=0) > 0.5
            if not m.any():
                continue
            hmax = float(s.height_mm[s.mask].max()) if s.mask.any() else 0.0
            hf = _fill_outside(s.height_mm, s.mask)
            af = _fill_outside(s.albedo, s.mask)
            hh = cv2.remap(hf, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            aa = cv2.remap(af, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            inside |= m
            height[m] = (hmax - hh[m])                 # depth behind the glass
            albedo[m] = aa[m]
        return albedo, height, inside

    def _render(self, area_mm, dpi, *, depth, with_truth):
        if depth not in (8, 16, None):
            raise ValueError(f"depth must be 8 or 16, got {depth}")
        x0, y0, x1, y1 = self._area(area_mm, dpi)
        pix = 25.4 / float(dpi)
        W = max(1, int(round((x1 - x0) / pix)))
        H = max(1, int(round((y1 - y0) / pix)))
        ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
        xs = x0 + (xs + 0.5) * pix
        ys = y0 + (ys + 0.5) * pix
        lid = max([it.surface.thickness_mm for it in self._items], default=0.0) + 0.5
        albedo, depth_mm, inside = self._face_maps(xs, ys, pix)
        # normals from the height (height = -depth) on the scan grid: n ∝ (-h_x, -h_y_up, 1)
        gr, gc = np.gradient(-depth_mm, pix)
        normals = np.dstack([-gc, gr, np.ones_like(gc)]).astype(np.float32)
        normals[~inside] = (0, 0, 1)
        normals /= np.linalg.norm(normals, axis=2, keepdims=True)
        # lid background: dark, textured, lit at the lid's depth
        tex = cv2.remap(self._lid_tex, (xs / 2).astype(np.float32), (ys / 2).astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
        lid_alb = self.lid_albedo * (1 + tex)
        albedo[~inside] = lid_alb[~inside, None]
        depth_mm[~inside] = lid
        # dust on the glass: small bright specks at depth 0 in front of everything
        near = ((self._dust[:, 0] > x0 - 1) & (self._dust[:, 0] < x1 + 1) & (self._dust[:, 1] > y0 - 1)
                & (self._dust[:, 1] < y1 + 1))
        for dx_, dy_, rad in self._dust[near]:
            j0, j1 = max(0, int((dx_ - rad - x0) / pix) - 2), min(W, int((dx_ + rad - x0) / pix) + 3)
            i0, i1 = max(0, int((dy_ - rad - y0) / pix) - 2), min(H, int((dy_ + rad - y0) / pix) + 3)
            if j0 >= j1 or i0 >= i1:
                continue
            win = np.s_[i0:i1, j0:j1]
            cov = np.clip((rad + pix / 2 - np.hypot(xs[win] - dx_, ys[win] - dy_)) / pix, 0, 1).astype(np.float32)
            albedo[win] = albedo[win] * (1 - cov[..., None]) + 0.7 * cov[..., None]
            depth_mm[win] = depth_mm[win] * (1 - cov)
        # shadows: march on a coarse grid (<= 0.5 mm), extended towards the lamp
        vis = None
        if self._items:
            cpix = max(pix, 0.5)
            reach = 3.0 * lid + 2 * cpix     # longer shadows come from lamp ends that carry little light
            # shadows exist only near objects: the grid covers the objects (+ reach) within the area
            obx0 = min(it.centre_mm[0] - self._radius_mm(it.surface) for it in self._items) - reach
            oby0 = min(it.centre_mm[1] - self._radius_mm(it.surface) for it in self._items) - reach
            obx1 = max(it.centre_mm[0] + self._radius_mm(it.surface) for it in self._items) + reach
            oby1 = max(it.centre_mm[1] + self._radius_mm(it.surface) for it in self._items) + reach
            cx0, cy0 = max(x0, obx0) - 2 * cpix, max(y0, oby0) - 2 * cpix
            cx1, cy1 = min(x1, obx1) + 2 * cpix, min(y1, oby1) + 2 * cpix
            cx1, cy1 = max(cx1, cx0 + 4 * cpix), max(cy1, cy0 + 4 * cpix)
            cx0, cy0 = cx0 - reach, cy0 - reach         # casters may lie outside the visible area
            cx1, cy1 = cx1 + reach, cy1 + reach
            cw, ch = int(np.ceil((cx1 - cx0) / cpix)), int(np.ceil((cy1 - cy0) / cpix))
            cys, cxs = np.mgrid[0:ch, 0:cw].astype(np.float64)
            cxs, cys = cx0 + (cxs + 0.5) * cpix, cy0 + (cys + 0.5) * cpix
            _, cdepth, cin = self._face_maps(cxs, cys, cpix)
            cdepth[~cin] = lid
            cvis = _shadow_visibility(cdepth, cin, cpix, self.lamp, lid, max_len_mm=reach)
            # sample the coarse visibility at the fine pixels
            mx = ((xs - cx0) / cpix - 0.5).astype(np.float32)
            my = ((ys - cy0) / cpix - 0.5).astype(np.float32)
            vis = np.stack([cv2.remap(v, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
                            for v in cvis])
        irr = lamp_irradiance(normals, depth_mm, self.lamp, visibility=vis)
        signal = albedo * irr[..., None] * np.float32(self.exposure)
        truth = None
        if with_truth:
            truth = RGBNImage(albedo=np.clip(albedo, 0, 1), mask=inside, dpi=dpi, normals=normals,
                              height_mm=np.where(inside, -depth_mm, 0).astype(np.float32))
            self._last_truth_shading = irr
        if depth is None:
            return None, truth
        sigma = np.sqrt(self.noise ** 2 * np.clip(signal, 0, None) + self.read_noise ** 2).astype(np.float32)
        noisy = signal + sigma * self.rng.standard_normal(signal.shape, dtype=np.float32)
        full = 65535 if depth == 16 else 255
        out = np.clip(np.rint(noisy * full), 0, full).astype(np.uint16 if depth == 16 else np.uint8)
        self.history.append(ScanRecord((x0, y0, x1, y1), float(dpi), [self.pose_of(it) for it in self._items],
                                       [it.surface for it in self._items]))
        return out, truth

    def pose_of(self, it: _Placed | int = 0) -> tuple[float, float, float]:
        """Pose (angle_deg, tx_mm, ty_mm) of a placed surface: fragment-frame mm → bed mm."""
        if isinstance(it, int):
            it = self._items[it]
        s = it.surface
        h, w = s.mask.shape
        c, sn = np.cos(np.deg2rad(it.angle_deg)), np.sin(np.deg2rad(it.angle_deg))
        centre_q = np.array([(w - 1) / 2, (h - 1) / 2]) * s.pixel_mm
        t = it.centre_mm - np.array([[c, -sn], [sn, c]]) @ centre_q
        return (float(it.angle_deg), float(t[0]), float(t[1]))


def scan_to_scan_affine(rec_from: ScanRecord, rec_to: ScanRecord, index: int = 0) -> np.ndarray:
    """True 2×3 affine mapping pixel (col, row) of scan ``rec_to`` to scan ``rec_from`` (ground truth).

    Both records must show the same object ``index`` (the same face); pixel centres follow the
    simulator's convention.
    """
    def pix_to_frag(rec):
        a, tx, ty = rec.poses[index]
        c, s = np.cos(np.deg2rad(a)), np.sin(np.deg2rad(a))
        p = 25.4 / rec.dpi
        R = np.array([[c, -s], [s, c]])
        # bed = A_pix [col,row,1] ; frag = R^T (bed - t)
        A = np.array([[p, 0, rec.area_mm[0] + 0.5 * p], [0, p, rec.area_mm[1] + 0.5 * p], [0, 0, 1]])
        T = np.eye(3)
        T[:2, :2] = R.T
        T[:2, 2] = -R.T @ np.array([tx, ty])
        return T @ A
    M = np.linalg.inv(pix_to_frag(rec_from)) @ pix_to_frag(rec_to)
    return M[:2]


def demo_surface(size_mm: float = 40.0, dpi: float = 300, *, relief_mm: float = 0.6, seed: int = 0,
                 thickness_mm: float = 8.0) -> FragmentSurface:
    """A fresco-like test fragment: irregular outline, painted bands and speckle, smooth relief.

    Used by tests and benchmarks (the synthetic fresco generator makes whole walls of these).
    """
    if size_mm <= 0 or dpi <= 0:
        raise ValueError("size_mm and dpi must be positive")
    rng = np.random.default_rng(seed)
    n = int(round(size_mm / 25.4 * dpi))
    yy, xx = np.mgrid[0:n, 0:n] / (n - 1) * 2 - 1
    ang = np.arctan2(yy, xx)
    rad = np.hypot(xx, yy)
    k = np.arange(1, 6)
    amp = rng.uniform(0.02, 0.08, 5)
    ph = rng.uniform(0, 2 * np.pi, 5)
    edge = 0.78 + np.tensordot(np.cos(np.multiply.outer(ang, k) + ph), amp, axes=([-1], [0]))
    mask = rad < edge
    pix = 25.4 / dpi
    # relief: smooth bumps and brush strokes (a few mm wide), plus a gentle dome
    noise = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.2 / pix)
    noise = noise / (noise.std() + 1e-12)
    strokes = np.sin(2 * np.pi * (xx * np.cos(0.6) + yy * np.sin(0.6)) * size_mm / 6.0)
    height = relief_mm * (0.5 * noise + 0.3 * strokes - 0.4 * rad ** 2)
    # albedo: ochre/red/blue bands with speckle
    base = np.array([[0.75, 0.55, 0.35], [0.65, 0.25, 0.2], [0.35, 0.45, 0.6]], np.float32)
    band = (np.floor((xx + 0.3 * yy + 1) * 2.5).astype(int)) % 3
    albedo = base[band]
    speck = ndimage.gaussian_filter(rng.normal(size=(n, n)), 0.15 / pix)
    albedo = albedo * (1 + 0.15 * (speck / (speck.std() + 1e-12)))[..., None]
    return FragmentSurface(albedo=np.clip(albedo, 0.05, 0.95).astype(np.float32),
                           height_mm=height.astype(np.float32), mask=mask, dpi=dpi, thickness_mm=thickness_mm)


def calibration_target(tilt_deg: float, azimuth_deg: float, *, size_mm: float = 8.0, dpi: float = 150,
                       albedo: float = 0.8) -> FragmentSurface:
    """A flat diffuse target tilted by ``tilt_deg`` towards ``azimuth_deg`` (§3.3.5).

    Its normal is ``(sin t cos φ, sin t sin φ, cos t)`` (x right, y up) when placed at angle 0.
    """
    if not 0 <= tilt_deg < 60:
        raise ValueError(f"tilt_deg must be in [0, 60), got {tilt_deg}")
    t, p = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
    nx, ny, nz = np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)
    n = max(8, int(round(size_mm / 25.4 * dpi)))
    pix = 25.4 / dpi
    rows, cols = np.mgrid[0:n, 0:n] * pix
    height = -(nx * cols - ny * rows) / nz          # y up = -row
    height -= height.max()
    mask = np.ones((n, n), bool)
    alb = np.full((n, n, 3), albedo, np.float32)
    return FragmentSurface(albedo=alb, height_mm=height.astype(np.float32), mask=mask, dpi=dpi,
                           thickness_mm=float(-height.min()) + 2.0)
