"""Registering every scan of a face to the target scan (§3.3.6).

The operator turns the fragment by roughly 90° between scans and it shifts a little, and the
shading changes with every rotation (the lamp stays put). Registration is therefore done on a
shading-tolerant image (:func:`registration_image`: gradients of the log chromaticity, which
shading does not change, plus a weaker log-luminance term for outlines and unpainted relief),
on copies reduced to about 0.08 mm per pixel (2× at 600 dpi, 4× at 1200 dpi); the fit is
sub-pixel there and so well below a pixel at full resolution. Steps:

1. coarse: align the fragment masks' centroids and search the angle (within ±20° of the previous
   scan's angle plus the nominal step, else all round) by normalised correlation on a ~0.4 mm grid;
2. fine: rigid inverse-compositional Lucas–Kanade (Baker & Matthews 2004) with a gain/offset fit,
   on a pyramid down to the working scale, sampling the moving image only at (a subsample of)
   the target's fragment pixels; the whole mask is used, outline included — it anchors the
   translation where the interior is striped or plain;
3. check: the correlation after alignment must exceed ``min_correlation``, else
   :class:`~common.acquisition.errors.RegistrationError` — a bad registration would emboss the
   normals, so it is refused.

OpenCV 5's ``findTransformECC``/``findTransformECCWithMask`` were tried first: on these images
they converged away from the true rotation even when started on it, so they are not used.

Transforms are 2×3 affines mapping target-scan pixel (col, row) to the moving scan's pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.acquisition.errors import RegistrationError
from common.acquisition.locate import fragment_mask, to_float


@dataclass
class Registration:
    """A scan registered to the target scan.

    Attributes
    ----------
    affine : (2, 3) float64
        Target pixel (col, row, 1) → this scan's pixel (col, row).
    angle_deg : float
        Rotation of the fragment in this scan relative to the target scan, clockwise on the image.
    correlation : float
        Normalised correlation of the registration images after alignment (1 = identical).
    residual : float
        RMS difference of the normalised registration images inside the fragment.
    """

    affine: np.ndarray
    angle_deg: float
    correlation: float
    residual: float


def registration_image(scan: np.ndarray, sigma_px: float = 1.5, luminance_weight: float = 0.1,
                       chroma_weight: float = 1.0) -> np.ndarray:
    """Shading-tolerant image for registration (float32).

    ``sqrt(|∇ G_σ * log chromaticity|² + w² |∇ G_σ * log luminance|²)``, smoothed (the log is
    taken before the blur ``G_σ``): under one white lamp a
    Lambertian surface's chromaticity does not depend on the shading, so painted edges register
    regardless of the light; the luminance term (weight ``w``) keeps the outline and the relief of
    unpainted surfaces.
    """
    img = to_float(scan)
    eps = 1e-3
    # log first, then blur: blurring the linear image mixes a bright lit flank with a dark one
    # across a groove, and the log of that mixture moves with the lamp side (a 0.35–0.6 px bias
    # between scans lit from different sides); the blurred log stays put (0.06–0.14 px)
    log = cv2.GaussianBlur(np.log(img + eps), (0, 0), sigma_px)
    lum = log.mean(axis=2)
    def grad2(a):
        gx = cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        gy = cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        return gx * gx + gy * gy
    g = luminance_weight ** 2 * grad2(lum)
    if chroma_weight > 0:
        for c in (0, 2):
            g += chroma_weight ** 2 * grad2(log[..., c] - log[..., 1])
    return cv2.GaussianBlur(np.sqrt(g), (0, 0), sigma_px)


def _rigid(angle_deg: float, centre_to: np.ndarray, centre_from: np.ndarray) -> np.ndarray:
    """Affine target→moving: rotate by angle about the target centre and move it to the moving centre."""
    c, s = np.cos(np.deg2rad(angle_deg)), np.sin(np.deg2rad(angle_deg))
    Q = np.array([[c, -s], [s, c]])
    return np.hstack([Q, (centre_from - Q @ centre_to)[:, None]])


def _to_level(M: np.ndarray, s: float) -> np.ndarray:
    """Full-resolution affine → affine on an image resized by ``s`` (pixel-centre convention)."""
    c = (1.0 / s - 1.0) / 2.0
    A, b = M[:, :2], M[:, 2]
    out = M.copy()
    out[:, 2] = s * (A @ np.array([c, c]) + b - c)
    return out


def _from_level(Ms: np.ndarray, s: float) -> np.ndarray:
    c = (1.0 / s - 1.0) / 2.0
    A, bs = Ms[:, :2], Ms[:, 2]
    out = Ms.copy()
    out[:, 2] = bs / s - A @ np.array([c, c]) + c
    return out


def _normalised(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    v = img[mask]
    return (img - v.mean()) / (v.std() + 1e-9)


def _coarse_angle(ft, mt, fm, mm, ct, cm, candidates, s):
    """Best angle of the candidates by masked normalised correlation at scale s."""
    H, W = ft.shape
    best, best_score = None, -np.inf
    tn = _normalised(ft, fm)
    for a in candidates:
        M = _to_level(_rigid(a, ct, cm), s)
        w = cv2.warpAffine(mt, M, (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        wm = cv2.warpAffine(mm.astype(np.uint8), M, (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
        both = fm & wm
        if both.sum() < 0.5 * fm.sum():
            continue
        score = float(np.mean(tn[both] * _normalised(w, both)[both])) * both.sum() / max(fm.sum(), 1)
        if score > best_score:
            best, best_score = a, score
    return best, best_score


def _sample(image: np.ndarray, q: np.ndarray, interp: int) -> np.ndarray:
    """Values of a 2-D image at points q = (x, y) (2, N); 0 outside (cv2.remap in 1024-wide rows)."""
    n = q.shape[1]
    rows = -(-n // 1024)
    mx = np.full(rows * 1024, -1e6, np.float32)
    my = np.full(rows * 1024, -1e6, np.float32)
    mx[:n], my[:n] = q[0], q[1]
    out = cv2.remap(image, mx.reshape(rows, 1024), my.reshape(rows, 1024), interp,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(-1)[:n]


def _refine_lk(template: np.ndarray, moving: np.ndarray, tmask: np.ndarray, mmask: np.ndarray, M: np.ndarray,
               iterations: int, tol_px: float = 0.01, max_points: int = 120_000) -> tuple[np.ndarray, float, float]:
    """Rigid inverse-compositional Lucas–Kanade (Baker & Matthews 2004) with gain/offset.

    Minimises Σ [(I(W(x; p)) − β)/α − T(x)]² over the rigid warp W (target → moving pixels),
    α, β re-fitted each iteration so a global change of brightness does not matter. The sum runs
    over the template mask, on a regular subsample of at most ``max_points`` pixels; the moving
    image is sampled only there (``cv2.remap``). Returns the refined 2×3 warp, the correlation of
    T and the warped I, and the RMS of their difference after normalisation (the residual).
    """
    ys, xs = np.nonzero(tmask)
    if len(xs) < 50:
        raise RegistrationError("too few fragment pixels to register")
    step = max(1, int(np.ceil(np.sqrt(len(xs) / max_points))))
    if step > 1:
        keep = (ys % step == 0) & (xs % step == 0)
        ys, xs = ys[keep], xs[keep]
    cx, cy = xs.mean(), ys.mean()
    gx = cv2.Sobel(template, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(template, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    X, Y = (xs - cx).astype(np.float32), (ys - cy).astype(np.float32)
    Tx, Ty, Tv = gx[ys, xs], gy[ys, xs], template[ys, xs]
    SD = np.stack([Tx * -Y + Ty * X, Tx, Ty], axis=1)          # d/d(theta, tx, ty) in centred coords
    C = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1.0]])
    Ci = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1.0]])
    M3 = np.vstack([M, [0, 0, 1.0]])
    r_max = float(np.sqrt((X * X + Y * Y).max()))
    pts = np.stack([xs, ys, np.ones_like(xs)]).astype(np.float64)
    mm8 = mmask.astype(np.uint8)
    corr, resid = -1.0, np.inf
    for _ in range(iterations):
        q = (M3[:2] @ pts).astype(np.float32)
        iv = _sample(moving, q, cv2.INTER_LINEAR)
        use = _sample(mm8, q, cv2.INTER_NEAREST) > 0
        if use.sum() < 50:
            raise RegistrationError("the scans do not overlap after alignment")
        iv, tv = iv[use], Tv[use]
        ti = tv - tv.mean()
        ii = iv - iv.mean()
        tt, vv, tv_ = float((ti * ti).sum()), float((ii * ii).sum()), float((ti * ii).sum())
        alpha = tv_ / max(tt, 1e-12)
        corr = tv_ / np.sqrt(max(tt * vv, 1e-24))
        resid = float(np.sqrt(max(2.0 - 2.0 * corr, 0.0)))     # RMS of the difference of the z-scores
        if alpha <= 0:
            raise RegistrationError(f"the scans do not match (correlation {corr:.2f}): they may show different "
                                    "faces or fragments; refusing to solve normals")
        err = ii / alpha - ti
        sd = SD[use]
        dp = np.linalg.solve(sd.T @ sd + 1e-9 * np.eye(3), sd.T @ err)
        th, tx, ty = dp
        Wd = np.array([[np.cos(th), -np.sin(th), tx], [np.sin(th), np.cos(th), ty], [0, 0, 1.0]])
        M3 = M3 @ C @ np.linalg.inv(Wd) @ Ci
        ang = np.arctan2(M3[1, 0], M3[0, 0])          # keep it rigid (numerical drift)
        M3[:2, :2] = [[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]]
        if abs(th) * r_max + np.hypot(tx, ty) < tol_px:
            break
    return M3[:2], float(corr), resid


def _shrink(img: np.ndarray, f: int, nearest: bool = False) -> np.ndarray:
    """Reduce by an integer factor exactly (crop the right/bottom remainder first), so that
    pixel centres map as p_full = f p + (f - 1)/2."""
    if f == 1:
        return img
    H, W = img.shape[:2]
    H2, W2 = max(f, H - H % f), max(f, W - W % f)
    img = img[:H2, :W2]
    if nearest:
        return cv2.resize(img.astype(np.uint8), (W2 // f, H2 // f), interpolation=cv2.INTER_NEAREST) > 0
    return cv2.resize(img, (W2 // f, H2 // f), interpolation=cv2.INTER_AREA)


@dataclass
class _Prepared:
    """A scan reduced to what registration needs, at the working scale ``scale``."""

    image: np.ndarray        # registration image at the working scale
    mask: np.ndarray         # fragment mask at the working scale
    centroid: np.ndarray     # fragment centroid, full-resolution pixels
    area_px: int             # fragment area, full-resolution pixels
    scale: float


def _working_scale(pixel_mm: float, target_mm: float = 0.08) -> float:
    """Scale at which registration works: about ``target_mm`` per pixel, never upsampled."""
    return 1.0 / max(1, int(round(target_mm / pixel_mm)))


def _prepare(scan: np.ndarray, mask: np.ndarray, dpi: float) -> _Prepared:
    mask = np.asarray(mask, bool)
    pixel_mm = 25.4 / dpi
    scale = _working_scale(pixel_mm)
    f = int(round(1 / scale))
    scan = np.asarray(scan)
    img = to_float(_shrink(np.ascontiguousarray(scan[..., :3]), f) if scan.ndim == 3 else _shrink(scan, f))
    m = _shrink(mask, f, nearest=True)
    mom = cv2.moments(mask.astype(np.uint8), binaryImage=True)
    area = mom["m00"]
    centroid = np.array([mom["m10"] / area, mom["m01"] / area]) if area else np.array([np.nan, np.nan])
    return _Prepared(registration_image(img), m, centroid, int(area), scale)


def _register(t: _Prepared, m: _Prepared, dpi: float, nominal_deg, search_deg, min_correlation) -> Registration:
    pixel_mm = 25.4 / dpi
    if t.area_px * pixel_mm ** 2 < 4 or m.area_px * pixel_mm ** 2 < 4:
        raise RegistrationError("no fragment visible in one of the scans (mask under 4 mm²); cannot register")
    area_ratio = m.area_px / t.area_px
    if not 0.8 < area_ratio < 1.25:
        raise RegistrationError(f"the fragment's visible area differs by {abs(1 - area_ratio):.0%} between scans; "
                                "the scans may show different faces or a moved/broken fragment")
    fs = t.scale
    ct, cm = t.centroid, m.centroid
    # coarse angle on a ~0.4 mm grid; the whole fragment including its outline is used throughout
    # (the outline anchors the translation where the interior is striped or plain)
    fc = max(1, int(round(0.4 / (pixel_mm / fs))))
    s = 1.0 / fc
    fts, fms = _shrink(t.image, fc), _shrink(m.image, fc)
    tms, mms = _shrink(t.mask, fc, nearest=True), _shrink(m.mask, fc, nearest=True)
    if nominal_deg is None:
        cand = np.arange(0, 360, 3.0)
    else:
        cand = nominal_deg + np.arange(-search_deg, search_deg + 0.1, 2.0)
    angle, _ = _coarse_angle(fts, fms, tms, mms, ct, cm, cand, s * fs)
    if angle is None:
        raise RegistrationError("no rotation makes the fragment outlines overlap; the scans may show different objects")
    step = 3.0 if nominal_deg is None else 2.0     # refine the grid to 0.5°
    angle, _ = _coarse_angle(fts, fms, tms, mms, ct, cm, angle + np.arange(-step + 0.5, step, 0.5), s * fs)
    M = _rigid(angle, ct, cm)
    # Lucas–Kanade pyramid down to the working scale
    levels = [l for l in (0.25, 0.5, 1.0) if l >= s * 0.99 or l == 1.0]
    corr, residual = -1.0, np.inf
    for lv in levels:
        fl = int(round(1 / lv))
        ftl, fml = _shrink(t.image, fl), _shrink(m.image, fl)
        tml, mml = _shrink(t.mask, fl, nearest=True), _shrink(m.mask, fl, nearest=True)
        Ml = _to_level(M, lv * fs)
        Ml, corr, residual = _refine_lk(ftl, fml, tml, mml, Ml, 40 if lv < 1.0 else 15)
        M = _from_level(Ml, lv * fs)
    angle_deg = float(np.degrees(np.arctan2(M[1, 0], M[0, 0])))
    if corr < min_correlation:
        raise RegistrationError(f"registration correlation {corr:.2f} is below {min_correlation:.2f} "
                                f"(rotation {angle_deg:.1f}°, residual {residual:.2f}); refusing to solve normals "
                                "from misaligned scans")
    return Registration(M, angle_deg, float(corr), float(residual))


def register_scan(target: np.ndarray, moving: np.ndarray, dpi: float, *, nominal_deg: float | None = None,
                  target_mask: np.ndarray | None = None, moving_mask: np.ndarray | None = None,
                  search_deg: float = 20.0, min_correlation: float = 0.6) -> Registration:
    """Rigid, sub-pixel registration of one scan to the target scan (rotation + translation).

    Parameters
    ----------
    target, moving : (H, W, 3) arrays
        Scans of the same face; shapes may differ.
    dpi : float
        Resolution of both scans (registration works at about 0.08 mm per pixel).
    nominal_deg : float or None
        Expected rotation of ``moving`` relative to ``target`` (clockwise on the image), e.g. 90;
        the angle is searched within ±``search_deg`` of it (None = all round).
    target_mask, moving_mask : bool arrays or None
        Fragment masks (None = :func:`~common.acquisition.locate.fragment_mask`).
    min_correlation : float
        Refuse (RegistrationError) below this normalised correlation after alignment.

    Returns
    -------
    Registration
    """
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    tm = fragment_mask(target, dpi) if target_mask is None else target_mask
    mm = fragment_mask(moving, dpi) if moving_mask is None else moving_mask
    return _register(_prepare(target, tm, dpi), _prepare(moving, mm, dpi), dpi, nominal_deg, search_deg,
                     min_correlation)


class TurnDirectionError(RegistrationError):
    """The scans do not register with the turns given, but do with turns the other way round.

    Attributes
    ----------
    turn : str
        ``"cw"`` or ``"ccw"``: the direction the scans were actually turned (clockwise on the image).
    registrations : list of Registration
        The registrations with that direction.
    """

    def __init__(self, message: str, turn: str, registrations: list):
        super().__init__(message)
        self.turn = turn
        self.registrations = registrations


class ScanOrderError(RegistrationError):
    """The scans register, but not in the order of their nominal rotations.

    Attributes
    ----------
    angles_deg : list of float
        Measured rotation of each scan relative to the first, clockwise on the image, in [0, 360).
    """

    def __init__(self, message: str, angles_deg: list):
        super().__init__(message)
        self.angles_deg = angles_deg


def _register_sequence(target, prepared, dpi, nominal_deg, search_deg, min_correlation, progress):
    out = [Registration(np.array([[1.0, 0, 0], [0, 1.0, 0]]), 0.0, 1.0, 0.0)]
    for i in range(1, len(prepared)):
        # each turn is ~90° ± 10°, so errors add up: expect this scan relative to the previous
        # scan's measured angle rather than to the nominal angle alone
        nom = None if nominal_deg is None else out[-1].angle_deg + nominal_deg[i] - nominal_deg[i - 1]
        try:
            out.append(_register(target, prepared[i], dpi, nom, search_deg, min_correlation))
        except RegistrationError as exc:
            where = f"nominal {nom:g}°" if nom is not None else "searched all round"
            err = RegistrationError(f"scan {i} ({where}): {exc}")
            err.index = i                # how far the sequence got: the best-explained failure is reported
            raise err from exc
        if progress:
            progress(i / max(1, len(prepared) - 1), f"registered scan {i}")
    return out


def _turn_name(nominal_deg) -> str:
    steps = np.diff(np.asarray(nominal_deg, float))
    return "cw" if steps.sum() >= 0 else "ccw"


_TURN_WORDS = {"cw": "clockwise", "ccw": "counter-clockwise"}


def _diagnose(target, prepared, dpi, nominal_deg, search_deg, min_correlation, failures):
    """Why a sequence with nominal rotations failed: turned the other way, or out of order? (None = neither.)

    Returns the registrations themselves when the scans register searched all round in the
    nominal order and direction, each turn within 60° of its nominal step (a rough operator).

    The failures of the other attempts are appended to ``failures``.
    """
    given = _turn_name(nominal_deg)
    other = "ccw" if given == "cw" else "cw"
    try:
        regs = _register_sequence(target, prepared, dpi, [-v for v in nominal_deg], search_deg, min_correlation, None)
        return TurnDirectionError(
            f"the scans look turned {_TURN_WORDS[other]}, not {_TURN_WORDS[given]} as their nominal rotations "
            f"{[float(v) for v in nominal_deg]} say: they register with {_TURN_WORDS[other]} turns (correlation "
            f"{min(r.correlation for r in regs[1:]):.2f}); give the turn direction as {other} "
            f"(tessera import scans --turn {other}) — rescanning is not needed", other, regs)
    except RegistrationError as exc:
        failures.append(exc)
    try:
        regs = _register_sequence(target, prepared, dpi, None, search_deg, min_correlation, None)
    except RegistrationError as exc:
        failures.append(exc)
        return None
    measured = [float(r.angle_deg % 360) for r in regs]
    steps = [((b - a + 180) % 360) - 180 for a, b in zip(measured[:-1], measured[1:])]
    nominal_steps = np.diff(np.asarray(nominal_deg, float))
    if all(abs(st - ns) <= 60 for st, ns in zip(steps, nominal_steps)):
        return regs          # the right order and direction, only turned roughly (e.g. 130° for 90°)
    if all(abs(st + ns) <= 60 for st, ns in zip(steps, nominal_steps)):
        return TurnDirectionError(
            f"the scans look turned {_TURN_WORDS[other]}, not {_TURN_WORDS[given]} as their nominal rotations "
            f"{[float(v) for v in nominal_deg]} say (measured {[round(v) for v in measured]}° clockwise); give the "
            f"turn direction as {other} (tessera import scans --turn {other}) — rescanning is not needed", other, regs)
    return ScanOrderError(
        f"the scans register, but their rotations relative to the first are {[round(v) for v in measured]}° "
        f"(clockwise), not the nominal {[float(v) for v in nominal_deg]}: they are out of turning order; give the "
        "scans in the order they were taken (or their rotations) — rescanning is not needed", measured)


def register_scans(scans: list, dpi: float, *, nominal_deg: list | None = None, masks: list | None = None,
                   progress=None, search_deg: float = 20.0, min_correlation: float = 0.6,
                   diagnose: bool = True, ambiguous_below: float = 0.95) -> list[Registration]:
    """Register every scan to the first (the target scan); the first gets the identity.

    ``nominal_deg`` are the nominal rotations of the scans (e.g. 0, 90, 180, 270, clockwise on
    the image); scan i is searched around the measured angle of scan i−1 plus the nominal step,
    since a person's errors in turning the fragment accumulate.

    When the scans do not register with the nominal rotations and ``diagnose`` is true, the
    failure is explained if it can be: :class:`TurnDirectionError` when they register with the
    turns the other way round (its ``registrations`` are usable), :class:`ScanOrderError` when
    they register searched all round but out of order. Scans that register searched all round in
    the nominal order and direction, each turn within 60° of the nominal step (turned 130° for
    90°), are simply returned. Otherwise the registration error stands
    (different faces or objects, a moved or broken fragment: that needs a rescan). A fragment that
    looks alike turned by 180° can also register the wrong way round, with a lower correlation:
    when the worst correlation is below ``ambiguous_below`` the other turn direction is tried too,
    and :class:`TurnDirectionError` raised if it fits clearly (by 0.05) better.
    """
    if len(scans) < 1:
        raise ValueError("scans must not be empty")
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    if nominal_deg is not None and len(nominal_deg) != len(scans):
        raise ValueError(f"nominal_deg must have one angle per scan ({len(scans)}), got {len(nominal_deg)}")
    masks = masks or [fragment_mask(s, dpi) for s in scans]
    prepared = [_prepare(s, m, dpi) for s, m in zip(scans, masks)]
    for i, p in enumerate(prepared):     # named by its own index (counted from 0), not as "one of the scans"
        if p.area_px * (25.4 / dpi) ** 2 < 4:
            raise RegistrationError(f"scan {i}: no fragment visible (mask under 4 mm²); cannot register — is the "
                                    "scan blank, or of an empty bed? Or does the piece fill the picture, with no bed "
                                    "around it to tell it from: scan it with a margin of bed on every side (pictures "
                                    "already cropped and registered go in with `tessera ps` or `tessera import images`)")
    try:
        regs = _register_sequence(prepared[0], prepared, dpi, nominal_deg, search_deg, min_correlation, progress)
    except RegistrationError as exc:
        if not diagnose or nominal_deg is None or len(scans) < 2:
            raise
        failures = [exc]
        found = _diagnose(prepared[0], prepared, dpi, nominal_deg, search_deg, min_correlation, failures)
        if isinstance(found, list):       # registered searched all round, in order: roughly turned, fine
            return found
        if isinstance(found, TurnDirectionError):
            raise TurnDirectionError(f"{found} (with the nominal turns: {exc})", found.turn,
                                     found.registrations) from exc
        if isinstance(found, ScanOrderError):
            raise ScanOrderError(f"{found} (with the nominal turns: {exc})", found.angles_deg) from exc
        # report the attempt that got furthest (turned the other way, it may fail only at the odd scan out)
        exc = max(failures, key=lambda e: getattr(e, "index", 0))
        raise RegistrationError(f"{exc}; the scans register neither turned the other way nor in another order "
                                "— rescan this face (all scans of one face, turning it the same way each time)") from exc
    # a fragment that looks alike turned by 180° (an oval, stripes) may also register, worse, with
    # turns the wrong way round: when the fit is not clearly good, compare with the other direction
    steps = np.diff(np.asarray(nominal_deg, float)) if nominal_deg is not None else np.zeros(0)
    worst = min((r.correlation for r in regs[1:]), default=1.0)
    if diagnose and worst < ambiguous_below and np.any(np.abs((steps + 90) % 180 - 90) > 1):
        try:
            other = _register_sequence(prepared[0], prepared, dpi, [-v for v in nominal_deg], search_deg,
                                       min_correlation, None)
        except RegistrationError:
            return regs
        other_worst = min(r.correlation for r in other[1:])
        if other_worst > worst + 0.05:
            given = _turn_name(nominal_deg)
            turn = "ccw" if given == "cw" else "cw"
            raise TurnDirectionError(
                f"the scans look turned {_TURN_WORDS[turn]}, not {_TURN_WORDS[given]} as their nominal rotations "
                f"{[float(v) for v in nominal_deg]} say: they register with correlation {other_worst:.2f} turned "
                f"{_TURN_WORDS[turn]} against {worst:.2f} as given; give the turn direction as {turn} "
                f"(tessera import scans --turn {turn}) — rescanning is not needed", turn, other)
    return regs


def turn_rotations(n: int, turn: str, step_deg: float = 90.0) -> list[float]:
    """Nominal rotations (clockwise on the image, in [0, 360)) of ``n`` scans turned by ``step_deg`` each time.

    ``turn`` is ``"cw"`` (0, 90, 180, 270) or ``"ccw"`` (0, 270, 180, 90).
    """
    if turn not in ("cw", "ccw"):
        raise ValueError(f"turn must be 'cw' or 'ccw', got {turn!r}")
    sign = 1.0 if turn == "cw" else -1.0
    return [float((sign * k * step_deg) % 360) for k in range(n)]


def register_turned(scans: list, dpi: float, turn: str = "auto", *, step_deg: float = 90.0,
                    masks: list | None = None, progress=None) -> tuple[str, list[Registration]]:
    """Register scans turned by ``step_deg`` between scans, clockwise, counter-clockwise or either.

    Parameters
    ----------
    scans : list of (H, W, 3) arrays
        The scans of one face in the order they were taken.
    dpi : float
    turn : {"cw", "ccw", "auto"}
        Direction the fragment was turned between scans, clockwise as seen on the scan image. With
        ``"auto"`` both are tried and the one that registers (better) is kept.

    Returns
    -------
    turn : str
        ``"cw"`` or ``"ccw"``: the direction used.
    registrations : list of Registration

    Raises
    ------
    TurnDirectionError
        ``turn`` was given, but the scans register (clearly better) the other way round; the
        message says which direction to give.
    ScanOrderError, RegistrationError
        As :func:`register_scans`.
    """
    if turn not in ("cw", "ccw", "auto"):
        raise ValueError(f"turn must be 'cw', 'ccw' or 'auto', got {turn!r}")
    first = "cw" if turn == "auto" else turn
    nominal = [k * step_deg * (1 if first == "cw" else -1) for k in range(len(scans))]
    try:
        return first, register_scans(scans, dpi, nominal_deg=nominal, masks=masks, progress=progress)
    except TurnDirectionError as exc:
        if turn == "auto":
            return exc.turn, exc.registrations
        raise


def warp_to_target(scan: np.ndarray, reg: Registration, shape: tuple[int, int]) -> np.ndarray:
    """Resample a scan (any dtype) into the target scan's frame (float32, full scale 1)."""
    img = to_float(scan)
    return cv2.warpAffine(img, reg.affine, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
