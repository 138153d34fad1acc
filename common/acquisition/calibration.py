"""Photometric calibration of a flatbed's lamp (§3.3.5).

A diffuse target of known albedo is scanned at known tilts (0–25°) and rotations; each scan gives
one sample (n, I) of the scanner's response to a surface orientation. The first-order model of
the thesis (eq. 3.4) is linear in the normal,

    I(n) = a · (n_x, n_y, n_z, 1),

fitted by least squares; a second-order model adds (n_x², n_y², n_x n_y, n_x n_z, n_y n_z). Both
are compared by leave-one-out cross-validation, and the first-order model is kept unless the
second is clearly better (the normal solve, eqs. 3.5–3.7, needs the linear one). A calibration
is stored per scanner as ``calibration/<scanner>/<UTC date>-<key>.h5`` (``tessera.calibration``)
and :func:`newest_calibration` returns the newest valid one.
"""

from __future__ import annotations

import datetime as _dt
import json
import re
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from common.acquisition.errors import CalibrationError
from common.acquisition.locate import fragment_mask, locate_fragment, to_float
from common.store import ArtifactError, ArtifactRef, Store, content_key

SCHEMA = "tessera.calibration"
SCHEMA_VERSION = 1
DEFAULT_TILTS = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0)
DEFAULT_AZIMUTHS = (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0)
#: the lamp fit and its leave-one-out cross-validation need at least this many target scans
MIN_TARGET_SCANS = 6


@dataclass
class Calibration:
    """A fitted lamp model of one scanner.

    Attributes
    ----------
    scanner : str
    a : (4,) float
        First-order coefficients of eq. 3.4 for albedo 1, in full-scale units (I in [0, 1]).
    second_order : (9,) float
        Coefficients of the second-order model (same basis + 5 quadratic terms).
    cv_rmse : dict
        Leave-one-out RMS prediction error of each model, ``{"first": .., "second": ..}``.
    order : int
        Model the cross-validation recommends (the solver uses the first-order one regardless).
    normals, intensities : (N, 3), (N,)
        The calibration samples.
    dpi, depth : scan settings used.
    report : list of dict
        Per target scan: name, tilt, direction, reading, clipped pixels, used or dropped (why), fit
        residual (:func:`fit_target_readings`).
    fit_rms : float
        RMS residual of the first-order fit over the used target scans (full scale 1, albedo 1).
    a_per_mm : (4,) float
        Change of ``a`` per millimetre of distance between the surface and the glass, fitted to the
        tilted targets' readings along their tilt (:func:`fit_target_readings`); zeros when not
        measured (a calibration by the inner median, the simulator's or a SANE device's). The lamp
        model at distance d is ``a + (d - a_depth_mm) a_per_mm`` (:func:`lamp_at_depth`).
    a_depth_mm : float
        Distance from the glass at which ``a`` was read (``--face-depth-mm``).
    date : str
        UTC ISO date-time of the calibration.
    """

    scanner: str
    a: np.ndarray
    second_order: np.ndarray
    cv_rmse: dict
    order: int
    normals: np.ndarray
    intensities: np.ndarray
    dpi: float = 150.0
    depth: int = 16
    date: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    target_albedo: float = 0.8
    id: str = ""
    report: list = field(default_factory=list)
    fit_rms: float = float("nan")
    a_per_mm: np.ndarray = field(default_factory=lambda: np.zeros(4))
    a_depth_mm: float = 0.0

    def predict(self, normals: np.ndarray, order: int = 1) -> np.ndarray:
        """Predicted reading of an albedo-1 surface with these normals (..., 3)."""
        X = _basis(np.asarray(normals, float), order)
        coef = self.a if order == 1 else self.second_order
        return X @ coef


def _basis(n: np.ndarray, order: int) -> np.ndarray:
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    cols = [nx, ny, nz, np.ones_like(nx)]
    if order == 2:
        cols += [nx * nx, ny * ny, nx * ny, nx * nz, ny * nz]
    return np.stack(cols, axis=-1)


def fit_lamp_model(normals: np.ndarray, intensities: np.ndarray, order: int = 1) -> np.ndarray:
    """Least-squares coefficients of the lamp model I(n) = a · (n_x, n_y, n_z, 1) (eq. 3.4).

    Parameters
    ----------
    normals : (N, 3) array
        Unit normals of the target (x right, y up, z to the sensor), N >= 4 (>= 9 for order 2).
    intensities : (N,) array
        Readings divided by the target's albedo.
    order : 1 or 2

    Returns
    -------
    (4,) or (9,) array
    """
    normals = np.asarray(normals, float)
    intensities = np.asarray(intensities, float)
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise ValueError(f"normals must be (N, 3), got {normals.shape}")
    if intensities.shape != normals.shape[:1]:
        raise ValueError(f"intensities must be ({normals.shape[0]},), got {intensities.shape}")
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    X = _basis(normals, order)
    if len(X) < X.shape[1]:
        raise ValueError(f"need at least {X.shape[1]} samples for order {order}, got {len(X)}")
    coef, *_ = np.linalg.lstsq(X, intensities, rcond=None)
    return coef


def cross_validate(normals: np.ndarray, intensities: np.ndarray) -> dict:
    """Leave-one-out RMS prediction error of the first- and second-order models (§3.3.5)."""
    normals = np.asarray(normals, float)
    intensities = np.asarray(intensities, float)
    out = {}
    for name, order in (("first", 1), ("second", 2)):
        X = _basis(normals, order)
        if len(X) <= X.shape[1]:
            out[name] = float("nan")
            continue
        # closed-form leave-one-out residuals of least squares: e_i / (1 - h_ii)
        coef, *_ = np.linalg.lstsq(X, intensities, rcond=None)
        resid = intensities - X @ coef
        hat = np.einsum("ij,ji->i", X, np.linalg.pinv(X))
        out[name] = float(np.sqrt(np.mean((resid / np.clip(1 - hat, 1e-9, None)) ** 2)))
    return out


def target_normal(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """Normal of a target tilted by ``tilt_deg`` towards ``azimuth_deg`` (x right, y up).

    ``(sin t cos φ, sin t sin φ, cos t)``: the normal leans towards the direction ``φ`` on the
    scan image, measured from the image's +x axis (columns, to the right) towards the image's
    top (rows decreasing), i.e. counter-clockwise as the image is displayed. The target lies
    face down on the glass, so its edge on that side is the one lifted off the glass. This is the
    convention of the ``tilt_direction_deg`` column of ``tessera calibrate --from-files``.
    """
    t, p = np.deg2rad(tilt_deg), np.deg2rad(azimuth_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


@dataclass
class TargetReading:
    """The target's reading in one scan (§3.3.5), with what the clipping check saw.

    Attributes
    ----------
    value : float
        Median reading over the central part of the target, full scale = 1 (mean of R, G, B).
    pixels : int
        Target pixels measured.
    clipped : int
        Of those, pixels with a channel at or above ``saturation`` of full scale or at 0 (the
        sensor's range clipped them: the median of such a scan is not the target's reading).
    whole_image : bool
        No background ring was found: the scan is a tight crop of the target, measured whole.
    slope_per_mm : float
        Change of the reading per millimetre of distance from the glass, from the fit along the
        tilt (NaN for an untilted target or a reading by the inner median).
    depth_mm : float
        Distance from the glass at which ``value`` was taken.
    """

    value: float
    pixels: int
    clipped: int
    whole_image: bool = False
    slope_per_mm: float = float("nan")
    depth_mm: float = 0.0

    @property
    def clipped_fraction(self) -> float:
        return self.clipped / max(self.pixels, 1)


def read_target(scan: np.ndarray, dpi: float, *, saturation: float = 0.98, tilt_deg: float = 0.0,
                direction_deg: float = 0.0, at_glass: bool = True, depth_mm: float = 0.0) -> TargetReading:
    """Reading of the calibration target where it lies on the glass, with its clipped pixels counted.

    The target is found by :func:`~common.acquisition.locate.fragment_mask` (the scan's outer ring
    is the bed); a scan cropped to the target itself (no ring of bed) has no such mask and is
    measured whole. Its inner part (the target shrunk by a quarter of its size on every side, away
    from its edges and their shadows) is used. An untilted target's reading is the median there.
    A tilted target lies on the glass along its edge opposite ``direction_deg`` and rises from it,
    and a scanner's light changes with the distance from the glass (about 1 % per mm), while a
    fragment's face lies on the glass: the reading is therefore fitted along the tilt direction,
    ``I(s) = c0 + c1 s`` with ``s`` the distance from that edge, and the reading at the height
    ``depth_mm`` above the glass returned, ``c0 + c1 depth_mm / tan(tilt)`` (a fragment rests on
    its highest points: its face lies on average some tenths of a millimetre above the glass). With ``at_glass=False`` the median of the inner part is returned whatever the
    tilt (the reading at the target's mean height above the glass).

    Parameters
    ----------
    scan : (H, W, 3) or (H, W) array
        uint8, uint16 or float (full scale 1).
    dpi : float
        Scan resolution.
    saturation : float
        A pixel with any channel at or above this fraction of full scale counts as clipped.
    tilt_deg, direction_deg : float
        The target's pose (:func:`target_normal`); direction on the image counter-clockwise from +x.
    at_glass : bool
        Read a tilted target at ``depth_mm`` above the glass (fit along the tilt direction).
    depth_mm : float
        Height above the glass at which the reading is taken (0 = the edge on the glass).
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    if not 0 < saturation <= 1:
        raise ValueError(f"saturation must be in (0, 1], got {saturation}")
    img = to_float(scan)
    mask = fragment_mask(scan, dpi)
    whole = False
    if mask.sum() < 16:
        # no target standing out from a ring of bed: a tight crop of the target (uniform), measured whole
        whole = True
        mask = np.ones(img.shape[:2], bool)
    rows, cols = np.nonzero(mask)
    size = min(np.ptp(rows), np.ptp(cols)) + 1
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=max(1, int(size // 4))) > 0
    if inner.sum() < 16:
        raise CalibrationError("calibration target not visible in its scan")
    ri, ci = np.nonzero(inner)
    px = img[ri, ci]
    clipped = int(((px >= saturation) | (px <= 0)).any(axis=1).sum())
    lum = px.mean(axis=1)
    value = float(np.median(lum))
    if at_glass and tilt_deg > 0.5:
        # distance from the edge lying on the glass, along the tilt direction (image: col right, row down)
        u = np.array([np.cos(np.deg2rad(direction_deg)), -np.sin(np.deg2rad(direction_deg))])
        s_all = cols * u[0] + rows * u[1]
        s = (ci * u[0] + ri * u[1] - s_all.min()) * 25.4 / dpi
        X = np.stack([np.ones_like(s), s], axis=1)
        coef, *_ = np.linalg.lstsq(X, lum, rcond=None)
        resid = lum - X @ coef
        keep = np.abs(resid) < 4 * 1.4826 * np.median(np.abs(resid)) + 1e-9     # dust, specks
        coef, *_ = np.linalg.lstsq(X[keep], lum[keep], rcond=None)
        slope = float(coef[1] / np.tan(np.deg2rad(tilt_deg)))       # per mm of distance from the glass
        value = float(coef[0] + slope * depth_mm)
        return TargetReading(value, int(len(px)), clipped, whole, slope_per_mm=slope, depth_mm=float(depth_mm))
    return TargetReading(value, int(len(px)), clipped, whole)


def measure_target(scan: np.ndarray, dpi: float) -> float:
    """Mean reading (full scale = 1) over the central part of the target in a scan (:func:`read_target`)."""
    return read_target(scan, dpi).value


def target_poses(tilts=DEFAULT_TILTS, azimuths=DEFAULT_AZIMUTHS) -> list[tuple[float, float]]:
    """The target's poses ``(tilt_deg, azimuth_deg)`` that :func:`calibrate_scanner` scans, in order.

    Tilt 0 is scanned once (every rotation of a flat target is the same pose); every other tilt at
    every rotation. Fewer than :data:`MIN_TARGET_SCANS` poses raise ValueError, before anything is scanned.
    """
    poses = [(0.0, 0.0)] + [(float(t), float(a)) for t in tilts if t > 0 for a in azimuths]
    if len(poses) < MIN_TARGET_SCANS:
        raise ValueError(f"tilts {', '.join(f'{t:g}' for t in tilts)} × azimuths {', '.join(f'{a:g}' for a in azimuths)} "
                         f"make {len(poses)} target pose(s); the lamp fit and its cross-validation need at least "
                         f"{MIN_TARGET_SCANS} (tilt 0 counts once)")
    return poses


def calibrate_scanner(scanner, operator: Callable[[float, float], None], *, tilts=DEFAULT_TILTS,
                      azimuths=DEFAULT_AZIMUTHS, dpi: float = 150, depth: int = 16, prescan_dpi: float = 50,
                      area_mm=None, target_albedo: float = 0.8, saturation: float = 0.98, max_clipped: float = 0.01,
                      progress: Callable[[float, str], None] | None = None) -> Calibration:
    """Scan the target at every tilt × rotation and fit the lamp model (§3.3.5).

    Parameters
    ----------
    scanner : Scanner
    operator : callable(tilt_deg, azimuth_deg)
        Sets the target up at that tilt and rotation; returns when done.
    tilts, azimuths : sequences of degrees
        Tilt 0 is scanned once (:func:`target_poses`).
    area_mm : tuple or None
        Where the calibration jig holds the target; None = find it with a pre-scan each time.
    target_albedo : float
        Diffuse reflectance of the target (readings are divided by it).
    saturation, max_clipped : float
        A target scan with more than ``max_clipped`` of its pixels clipped (a channel at or above
        ``saturation`` of full scale, or at 0) is dropped from the fit and listed in
        ``Calibration.report`` (:func:`fit_target_readings`).
    progress : callable(fraction, text), optional
        Called after each target scan with the fraction of poses done and the pose just scanned.
    """
    poses = target_poses(tilts, azimuths)
    readings = []
    for i, (t, a) in enumerate(poses):
        operator(t, a)
        area = area_mm
        if area is None:
            pre = scanner.scan(None, prescan_dpi, depth)
            area = locate_fragment(pre, prescan_dpi, margin_mm=3.0, bed_mm=scanner.bed_mm)
        img = scanner.scan(area, dpi, depth)
        # the station's own path keeps the inner median (its figures were measured so); --from-files
        # reads at the glass (issue 16: a held-out scanner's lamp whose light changes with height)
        readings.append(read_target(img, dpi, saturation=saturation, tilt_deg=t, direction_deg=a, at_glass=False))
        if progress:
            progress((i + 1) / len(poses), f"target at tilt {t:g}°, rotation {a:g}°")
    return fit_target_readings(getattr(scanner, "name", "scanner"), readings, [p[0] for p in poses],
                               [p[1] for p in poses], names=[f"tilt {t:g}° rotation {a:g}°" for t, a in poses],
                               dpi=dpi, depth=depth, target_albedo=target_albedo, max_clipped=max_clipped)


def fit_target_readings(scanner: str, readings: list, tilts_deg, directions_deg, *, names=None,
                        target_albedo: float = 0.8, max_clipped: float = 0.01, dpi: float = 150.0,
                        depth: int = 16) -> Calibration:
    """Fit the lamp model to target readings, dropping clipped ones; per-reading report (§3.3.5).

    Parameters
    ----------
    scanner : str
        Device name the calibration is stored under.
    readings : list of TargetReading
        One per target scan (:func:`read_target`).
    tilts_deg, directions_deg : sequences of float
        The target's tilt and tilt direction in each scan (:func:`target_normal`: the normal leans
        towards ``direction`` measured from the image's +x axis, counter-clockwise on the image).
    names : list of str or None
        How each reading is called in the report (file names).
    target_albedo : float
        Diffuse reflectance of the target; readings are divided by it.
    max_clipped : float
        Readings with a larger fraction of clipped pixels are dropped (a clipped median is not the
        target's reading; the issue measured 0.36° → 0.29° median normal error by dropping them).

    Returns
    -------
    Calibration
        With ``report``: one dict per reading — ``name, tilt_deg, direction_deg, value, pixels,
        clipped, used, reason, residual`` (measured minus first-order prediction, albedo 1, full
        scale 1), ``slope_per_mm`` — and ``fit_rms`` (RMS residual over the used readings); with
        ``a_per_mm`` fitted to the readings' slopes with the distance from the glass when at least
        6 used readings have one (targets read along their tilt, :func:`read_target`), else zeros.

    Raises
    ------
    CalibrationError
        Fewer than 6 usable readings, or an unphysical fit.
    """
    n = len(readings)
    tilts = np.asarray(tilts_deg, float)
    dirs = np.asarray(directions_deg, float)
    if tilts.shape != (n,) or dirs.shape != (n,):
        raise ValueError(f"tilts_deg and directions_deg must have {n} entries (one per reading), "
                         f"got {tilts.shape} and {dirs.shape}")
    if not 0 < target_albedo <= 1:
        raise ValueError(f"target_albedo must be in (0, 1], got {target_albedo}")
    names = list(names) if names is not None else [f"reading {i}" for i in range(n)]
    normals = np.array([target_normal(t, d) for t, d in zip(tilts, dirs)]).reshape(n, 3)
    values = np.array([r.value for r in readings], float) / target_albedo
    used = np.array([r.clipped_fraction <= max_clipped for r in readings], bool)
    report = []
    for i, r in enumerate(readings):
        reason = "" if used[i] else (f"{r.clipped} of {r.pixels} target pixels clipped "
                                     f"({r.clipped_fraction:.1%} > {max_clipped:.1%})")
        report.append({"name": names[i], "tilt_deg": float(tilts[i]), "direction_deg": float(dirs[i]),
                       "value": float(r.value), "pixels": int(r.pixels), "clipped": int(r.clipped),
                       "whole_image": bool(r.whole_image), "used": bool(used[i]), "reason": reason})
    if used.sum() < MIN_TARGET_SCANS:
        dropped = "; ".join(f"{e['name']}: {e['reason']}" for e in report if not e["used"])
        raise CalibrationError(f"only {int(used.sum())} of {n} target scans are usable, at least {MIN_TARGET_SCANS} are needed"
                               + (f" (dropped: {dropped})" if dropped else "")
                               + "; lower the scanner's exposure or add target scans")
    cal = fit_calibration(scanner, normals[used], values[used], dpi=dpi, depth=depth, target_albedo=target_albedo)
    # how the lamp changes with the distance from the glass: d I / d z = a_per_mm . (n, 1) at each
    # tilted target (eq. 3.4 holds at every distance, so its derivative is linear in n too)
    slopes = np.array([r.slope_per_mm for r in readings], float) / target_albedo
    with_slope = used & np.isfinite(slopes)
    if with_slope.sum() >= 6:
        cal.a_per_mm = fit_lamp_model(normals[with_slope], slopes[with_slope], 1)
        cal.a_depth_mm = float(np.median([r.depth_mm for r, u in zip(readings, with_slope) if u]))
    resid = values - cal.predict(normals)
    for e, r, sl in zip(report, resid, slopes):
        e["residual"] = float(r)
        e["slope_per_mm"] = None if not np.isfinite(sl) else float(sl)
    cal.report = report
    cal.fit_rms = float(np.sqrt(np.mean(resid[used] ** 2)))
    return cal


def lamp_at_depth(cal: Calibration, depth_mm) -> np.ndarray:
    """First-order lamp coefficients at a distance from the glass: ``a + (d - a_depth_mm) a_per_mm``.

    A flatbed's light changes with the distance of the surface from the glass (the lamp is a few
    millimetres below it and aimed at the sensor line; about 1–2 % per mm on the benchmark's
    scanner), and a fragment resting on its highest points holds its face at 0–1.5 mm. Eq. 3.4 is
    linear in n at every distance; the tilted targets measure its change per mm
    (:func:`fit_target_readings`).

    Parameters
    ----------
    cal : Calibration
    depth_mm : float or (M,) array
        Distance(s) of the surface from the glass, mm.

    Returns
    -------
    (4,) or (M, 4) float
    """
    d = np.asarray(depth_mm, float)
    return np.asarray(cal.a, float) + (d[..., None] - cal.a_depth_mm) * np.asarray(cal.a_per_mm, float)


def fit_calibration(scanner: str, normals: np.ndarray, intensities: np.ndarray, **kw) -> Calibration:
    """Fit both models to calibration samples and cross-validate them."""
    a = fit_lamp_model(normals, intensities, 1)
    q = fit_lamp_model(normals, intensities, 2) if len(normals) >= 9 else np.r_[a, np.zeros(5)]
    cv = cross_validate(normals, intensities)
    # keep the first-order model unless the second predicts clearly (>25 %) better
    order = 2 if np.isfinite(cv["second"]) and cv["second"] < 0.75 * cv["first"] else 1
    if a[2] + a[3] <= 0 or not np.all(np.isfinite(a)):
        raise CalibrationError(f"calibration fit is not physical (a = {a}); check the target scans")
    if a[2] <= 0:      # eq. 3.7 divides by a_z: the normal solve needs the reading to grow with n_z
        raise CalibrationError(f"calibration fit is not usable: a_z = {a[2]:.4f} <= 0 (the readings do not fall as "
                               "the target tilts away from the sensor); check the tilt columns, the target's "
                               "flatness and that the exposure did not change between scans")
    return Calibration(scanner=scanner, a=a, second_order=q, cv_rmse=cv, order=order, normals=normals,
                       intensities=intensities, **kw)


def simulated_target_operator(sim, *, centre_mm=(60.0, 60.0), size_mm: float = 4.0, dpi: float = 300) -> Callable:
    """Operator for the simulated flatbed: puts the tilted target in the jig (fixed place, angle 0)."""
    from common.acquisition.flatbed_sim import calibration_target

    def act(tilt, azimuth):
        sim.place(calibration_target(tilt, azimuth, size_mm=size_mm, dpi=dpi), angle_deg=0.0, centre_mm=centre_mm)
    return act


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "scanner"


def save_calibration(store: Store, cal: Calibration) -> ArtifactRef:
    """Store as ``calibration/<scanner>/<UTC date>-<key>.h5`` (schema ``tessera.calibration``)."""
    stamp = _dt.datetime.fromisoformat(cal.date).astimezone(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    key = content_key(cal.scanner, cal.date, np.asarray(cal.a).tobytes().hex(), cal.intensities.tobytes().hex())
    relpath = f"calibration/{_safe(cal.scanner)}/{stamp}-{key}.h5"

    def fill(f):
        f.attrs["scanner"] = cal.scanner
        f.attrs["date"] = cal.date
        f.attrs["order"] = cal.order
        f.attrs["cv_rmse"] = json.dumps(cal.cv_rmse)
        f.attrs["dpi"] = cal.dpi
        f.attrs["depth"] = cal.depth
        f.attrs["target_albedo"] = cal.target_albedo
        f.attrs["model"] = "I(n) = a . (nx, ny, nz, 1), normals x right, y up, z to sensor, I full scale = 1"
        f.attrs["report"] = json.dumps(cal.report)
        f.attrs["fit_rms"] = float(cal.fit_rms)
        f.attrs["a_depth_mm"] = float(cal.a_depth_mm)
        f.create_dataset("a_per_mm", data=np.asarray(cal.a_per_mm, float))
        f.create_dataset("a", data=np.asarray(cal.a, float))
        f.create_dataset("second_order", data=np.asarray(cal.second_order, float))
        f.create_dataset("normals", data=cal.normals)
        f.create_dataset("intensities", data=cal.intensities)
    ref = store.write(relpath, SCHEMA, SCHEMA_VERSION, fill, provenance={"device": cal.scanner})
    cal.id = relpath
    return ref


def load_calibration(store: Store, ref) -> Calibration:
    """Read a ``tessera.calibration`` artifact."""
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        try:
            cal = Calibration(scanner=str(f.attrs["scanner"]), a=f["a"][()], second_order=f["second_order"][()],
                              cv_rmse=json.loads(f.attrs["cv_rmse"]), order=int(f.attrs["order"]),
                              normals=f["normals"][()], intensities=f["intensities"][()], dpi=float(f.attrs["dpi"]),
                              depth=int(f.attrs["depth"]), date=str(f.attrs["date"]),
                              target_albedo=float(f.attrs["target_albedo"]),
                              report=json.loads(f.attrs.get("report", "[]")),
                              fit_rms=float(f.attrs.get("fit_rms", float("nan"))),
                              a_per_mm=f["a_per_mm"][()] if "a_per_mm" in f else np.zeros(4),
                              a_depth_mm=float(f.attrs.get("a_depth_mm", 0.0)))
        except KeyError as exc:
            raise ArtifactError(f"calibration {f.filename} lacks {exc}") from exc
    cal.id = ref.path if isinstance(ref, ArtifactRef) else str(ref)
    return cal


def newest_calibration(store: Store, scanner: str) -> tuple[Calibration, ArtifactRef]:
    """The newest valid calibration of ``scanner``; unreadable or unphysical files are skipped.

    Raises
    ------
    CalibrationError
        When the scanner has no valid calibration (run ``tessera calibrate``).
    """
    folder = store.path(f"calibration/{_safe(scanner)}")
    names = sorted((p.name for p in folder.glob("*.h5")), reverse=True) if folder.is_dir() else []
    problems = []
    for name in names:      # file names start with the UTC time stamp: newest first
        rel = f"calibration/{_safe(scanner)}/{name}"
        try:
            ref = store.ref(rel)
            cal = load_calibration(store, ref)
            a = np.asarray(cal.a, float)
            if a.shape != (4,) or not np.all(np.isfinite(a)) or a[2] + a[3] <= 0:
                raise CalibrationError(f"coefficients {a} are not usable")
            return cal, ref
        except (ArtifactError, CalibrationError, OSError) as exc:
            problems.append(f"{name}: {exc}")
    detail = f" (skipped: {'; '.join(problems)})" if problems else ""
    raise CalibrationError(f"no valid calibration for scanner {scanner!r} under {folder}{detail}; run `tessera calibrate`")


#: First-order lamp model of the project's simulated flatbed (docs/flatbed.md, "Calibration"):
#: a = (0.000, 0.349, 0.494, 0.255) measured by ``tessera calibrate`` on the simulator, its lamp
#: towards the image's top. Its in-plane strength and the (a_z, a_w) pair are a flatbed lamp's
#: nominal shape; :func:`nominal_calibration` turns it to another scanner's lamp side.
NOMINAL_A = (0.000, 0.349, 0.494, 0.255)


def nominal_calibration(scanner: str, lamp_direction_deg: float, *, dpi: float = 150.0) -> Calibration:
    """A nominal lamp model for a scanner with no target scans: :data:`NOMINAL_A` turned to its lamp side.

    Without scans of a tilted target (§3.3.5) nothing measures a scanner's lamp; what its scans do
    show is the side the light comes from (the shadow beside a thick object falls on the lamp's far
    side, :func:`lamp_direction_from_shadows`). The model keeps the simulator's strengths and
    points its in-plane part there: a = (s cos φ, s sin φ, a_z, a_w) with s = |(a_x, a_y)|.
    Normals solved with it have the right in-plane frame up to the error in φ, and a tilt scale
    that is only nominal: use it for relief (illustrations), not for measured angles.

    Parameters
    ----------
    scanner : str
        Device name the calibration is stored under.
    lamp_direction_deg : float
        Direction towards the lamp on the scan image as displayed, degrees counter-clockwise from
        the image's +x axis (0 = right, 90 = top), the convention of ``calibrate --from-files``.

    Returns
    -------
    Calibration
        With ``report`` saying it is nominal and ``fit_rms`` NaN (nothing was fitted).
    """
    if not np.isfinite(lamp_direction_deg):
        raise ValueError(f"lamp_direction_deg must be a number, got {lamp_direction_deg}")
    a0 = np.asarray(NOMINAL_A, float)
    s = float(np.hypot(a0[0], a0[1]))
    phi = np.radians(lamp_direction_deg)
    a = np.array([s * np.cos(phi), s * np.sin(phi), a0[2], a0[3]])
    a[np.abs(a) < 1e-12] = 0.0
    return Calibration(scanner=scanner, a=a, second_order=np.r_[a, np.zeros(5)],
                       cv_rmse={"first": float("nan"), "second": float("nan")}, order=1,
                       normals=np.zeros((0, 3)), intensities=np.zeros(0), dpi=dpi,
                       report=[{"nominal": True, "lamp_direction_deg": float(lamp_direction_deg),
                                "model": f"NOMINAL_A {list(NOMINAL_A)} turned to {lamp_direction_deg:g} deg"}])


def lamp_direction_from_shadows(scans: list, masks: list, dpi: float, *, ring_mm: tuple = (0.5, 10.0)) -> tuple[float, float]:
    """Direction towards a flatbed's lamp from the shadows beside the fragment in its scans.

    The lamp moves with the sensor, so in every scan it lights the object from the same side of
    the image and its shadow falls on the far side, whichever way the object was turned. In a ring
    ``ring_mm`` outside each mask, the darkening below the bed's level (the ring's 80th percentile
    of luminance) is taken; the scans' darkening maps are added up aligned on the masks' centroids
    **without turning them**, so the scanner's shadow adds up while what turns with the fragment
    (shade under a lifted edge, its own dark rim) averages out. The lamp is opposite the weighted
    mean offset of the summed darkening from the centre.

    Parameters
    ----------
    scans : list of (H, W, 3) arrays
        The turned scans of one face.
    masks : list of (H, W) bool
        The fragment in each (e.g. :func:`~common.acquisition.locate.face_masks`).
    dpi : float
    ring_mm : (inner, outer)
        Distances from the mask between which shadow is looked for, mm.

    Returns
    -------
    direction_deg : float
        Towards the lamp, counter-clockwise from the image's +x axis (0 = right, 90 = top), in [0, 360).
    agreement : float
        Length of the mean of the scans' own unit vectors (1 = every scan alone points the same
        way; low when shade that turns with the fragment dominates single scans).

    Raises
    ------
    ValueError
        No darkening beside the fragment in any scan.
    """
    if len(scans) != len(masks) or not scans:
        raise ValueError("give one mask per scan, and at least one scan")
    px = dpi / 25.4
    r_in, r_out = (max(1, int(round(r * px))) for r in ring_mm)
    maps, vs = [], []
    for scan, m in zip(scans, masks):
        m8 = np.asarray(m, np.uint8)
        if not m8.any():
            continue
        lum = to_float(scan).mean(axis=2)
        # the ring by the distance to the mask (linear time; a dilation by a 10 mm disc costs its area per pixel)
        dist = cv2.distanceTransform((m8 == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        ring = (dist > r_in) & (dist <= r_out)
        if not ring.any():
            continue
        bed = float(np.percentile(lum[ring], 80))
        w = (np.clip(bed - lum, 0, None) * ring).astype(np.float32)
        ys, xs = np.nonzero(m8)
        cy, cx = ys.mean(), xs.mean()
        maps.append((w, cx, cy))
        yy, xx = np.mgrid[0:lum.shape[0], 0:lum.shape[1]]
        v = np.array([(w * (xx - cx)).sum(), -(w * (yy - cy)).sum()])
        if np.hypot(*v) > 0:
            vs.append(v / np.hypot(*v))
    if not vs:
        raise ValueError("no shadow beside the fragment in any scan: the lamp side cannot be read from these scans")
    R = max(max(w.shape) for w, _, _ in maps)
    acc = np.zeros((2 * R + 1, 2 * R + 1), np.float32)
    for w, cx, cy in maps:      # translate each map so that its centroid lands on the centre, no turning
        M = np.float32([[1, 0, R - cx], [0, 1, R - cy]])
        acc += cv2.warpAffine(w, M, acc.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=0)
    yy, xx = np.mgrid[0:acc.shape[0], 0:acc.shape[1]]
    v = np.array([(acc * (xx - R)).sum(), -(acc * (yy - R)).sum()])
    return float(np.degrees(np.arctan2(-v[1], -v[0])) % 360), float(np.hypot(*np.mean(vs, axis=0)))
