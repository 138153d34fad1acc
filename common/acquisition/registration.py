"""Registering every scan of a face to the target scan (§3.3.6).

The operator turns the fragment by roughly 90° between scans and it shifts a little, and the
shading changes with every rotation (the lamp stays put). Registration is therefore done on a
shading-tolerant image: the smoothed gradient magnitude of the log luminance (albedo edges
survive a change of light, gain and offset do not matter to the correlation). Steps:

1. coarse: align the fragment masks' centroids and search the angle (around the nominal
   rotation if known, else all round) by normalised correlation on a ~0.4 mm grid;
2. fine: a pyramid of rigid inverse-compositional Lucas–Kanade refinements (Baker & Matthews 2004)
   with a gain/offset fit, down to full resolution, for a sub-pixel rotation + translation;
3. check: the correlation after alignment must exceed ``min_correlation``, else
   :class:`~common.acquisition.errors.RegistrationError` — a bad registration would emboss the
   normals, so it is refused.

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


def registration_image(scan: np.ndarray, sigma_px: float = 1.5, luminance_weight: float = 0.5,
                       chroma_weight: float = 1.0) -> np.ndarray:
    """Shading-tolerant image for registration (float32).

    ``sqrt(|∇ log chromaticity|² + w² |∇ log luminance|²)``, smoothed: under one white lamp a
    Lambertian surface's chromaticity does not depend on the shading, so painted edges register
    regardless of the light; the luminance term (weight ``w``) keeps the outline and the relief of
    unpainted surfaces.
    """
    img = to_float(scan)
    img = cv2.GaussianBlur(img, (0, 0), sigma_px)
    eps = 1e-3
    log = np.log(img + eps)
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


def _refine_lk(template: np.ndarray, moving: np.ndarray, tmask: np.ndarray, mmask: np.ndarray, M: np.ndarray,
               iterations: int, tol_px: float = 0.005) -> tuple[np.ndarray, float]:
    """Rigid inverse-compositional Lucas–Kanade (Baker & Matthews 2004) with gain/offset.

    Minimises Σ [(I(W(x; p)) − β)/α − T(x)]² over the rigid warp W (target → moving pixels),
    α, β re-fitted each iteration so a global change of brightness does not matter. Returns
    the refined 2×3 warp and the correlation of T and the warped I over the used pixels.
    """
    H, W = template.shape
    ys, xs = np.nonzero(tmask)
    if len(xs) < 50:
        raise RegistrationError("too few fragment pixels to register")
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
    corr = -1.0
    for _ in range(iterations):
        Iw = cv2.warpAffine(moving, M3[:2], (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        vw = cv2.warpAffine(mmask.astype(np.uint8), M3[:2], (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
        use = vw[ys, xs] > 0
        if use.sum() < 50:
            raise RegistrationError("the scans do not overlap after alignment")
        iv, tv = Iw[ys, xs][use], Tv[use]
        ti = tv - tv.mean()
        ii = iv - iv.mean()
        alpha = float((ti * ii).sum() / max((ti * ti).sum(), 1e-12))
        corr = float((ti * ii).sum() / np.sqrt(max((ti * ti).sum() * (ii * ii).sum(), 1e-24)))
        if alpha <= 0:
            raise RegistrationError(f"registration images are anti-correlated (r = {corr:.2f})")
        err = ii / alpha - ti
        sd = SD[use]
        Hm = sd.T @ sd
        dp = np.linalg.solve(Hm + 1e-9 * np.eye(3), sd.T @ err)
        th, tx, ty = dp
        Wd = np.array([[np.cos(th), -np.sin(th), tx], [np.sin(th), np.cos(th), ty], [0, 0, 1.0]])
        M3 = M3 @ C @ np.linalg.inv(Wd) @ Ci
        # keep it rigid (numerical drift)
        ang = np.arctan2(M3[1, 0], M3[0, 0])
        M3[:2, :2] = [[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]]
        if abs(th) * r_max + np.hypot(tx, ty) < tol_px:
            break
    return M3[:2], corr


def register_scan(target: np.ndarray, moving: np.ndarray, dpi: float, *, nominal_deg: float | None = None,
                  target_mask: np.ndarray | None = None, moving_mask: np.ndarray | None = None,
                  search_deg: float = 20.0, min_correlation: float = 0.6) -> Registration:
    """Rigid, sub-pixel registration of one scan to the target scan (rotation + translation).

    Parameters
    ----------
    target, moving : (H, W, 3) arrays
        Scans of the same face; shapes may differ.
    dpi : float
        Resolution of both scans.
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
    tm = fragment_mask(target, dpi) if target_mask is None else np.asarray(target_mask, bool)
    mm = fragment_mask(moving, dpi) if moving_mask is None else np.asarray(moving_mask, bool)
    pixel_mm = 25.4 / dpi
    if tm.sum() * pixel_mm ** 2 < 4 or mm.sum() * pixel_mm ** 2 < 4:
        raise RegistrationError("no fragment visible in one of the scans (mask under 4 mm²); cannot register")
    area_ratio = mm.sum() / tm.sum()
    if not 0.8 < area_ratio < 1.25:
        raise RegistrationError(f"the fragment's visible area differs by {abs(1 - area_ratio):.0%} between scans; "
                                "the scans may show different faces or a moved/broken fragment")
    ft, fmv = registration_image(target), registration_image(moving)
    ys, xs = np.nonzero(tm)
    ct = np.array([xs.mean(), ys.mean()])
    ys, xs = np.nonzero(mm)
    cm = np.array([xs.mean(), ys.mean()])
    # the whole fragment including its outline: the outline anchors the translation where the
    # interior is striped or plain (interior-only masks let it slide along stripes)
    tin, min_ = tm, mm
    # coarse angle on a ~0.4 mm grid
    s = min(1.0, pixel_mm / 0.4)
    size = lambda a: (max(8, int(round(a.shape[1] * s))), max(8, int(round(a.shape[0] * s))))
    fts, fms = cv2.resize(ft, size(ft), interpolation=cv2.INTER_AREA), cv2.resize(fmv, size(fmv), interpolation=cv2.INTER_AREA)
    tms = cv2.resize(tin.astype(np.uint8), size(ft), interpolation=cv2.INTER_NEAREST) > 0
    mms = cv2.resize(mm.astype(np.uint8), size(fmv), interpolation=cv2.INTER_NEAREST) > 0
    if nominal_deg is None:
        cand = np.arange(0, 360, 3.0)
    else:
        cand = nominal_deg + np.arange(-search_deg, search_deg + 0.1, 1.0)
    angle, _ = _coarse_angle(fts, fms, tms, mms, ct, cm, cand, s)
    if angle is None:
        raise RegistrationError("no rotation makes the fragment outlines overlap; the scans may show different objects")
    if nominal_deg is None:    # refine the 3° grid
        angle, _ = _coarse_angle(fts, fms, tms, mms, ct, cm, angle + np.arange(-2, 2.1, 0.5), s)
    M = _rigid(angle, ct, cm)
    # Lucas–Kanade pyramid down to full resolution
    levels = [l for l in (0.25, 0.5, 1.0) if l >= s * 0.99 or l == 1.0]
    corr = -1.0
    for lv in levels:
        if lv < 1.0:
            ftl = cv2.resize(ft, (int(ft.shape[1] * lv), int(ft.shape[0] * lv)), interpolation=cv2.INTER_AREA)
            fml = cv2.resize(fmv, (int(fmv.shape[1] * lv), int(fmv.shape[0] * lv)), interpolation=cv2.INTER_AREA)
            tml = cv2.resize(tin.astype(np.uint8), (ftl.shape[1], ftl.shape[0]), interpolation=cv2.INTER_NEAREST)
            mml = cv2.resize(min_.astype(np.uint8), (fml.shape[1], fml.shape[0]), interpolation=cv2.INTER_NEAREST)
        else:
            ftl, fml, tml, mml = ft, fmv, tin.astype(np.uint8), min_.astype(np.uint8)
        Ml = _to_level(M, lv)
        Ml, corr = _refine_lk(ftl, fml, tml > 0, mml > 0, Ml, 40 if lv < 1.0 else 8)
        M = _from_level(Ml, lv)
    warped = cv2.warpAffine(fmv, M, (ft.shape[1], ft.shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    a, b = _normalised(ft, tin), _normalised(warped, tin)
    residual = float(np.sqrt(np.mean((a[tin] - b[tin]) ** 2)))
    angle_deg = float(np.degrees(np.arctan2(M[1, 0], M[0, 0])))
    if corr < min_correlation:
        raise RegistrationError(f"registration correlation {corr:.2f} is below {min_correlation:.2f} "
                                f"(rotation {angle_deg:.1f}°, residual {residual:.2f}); refusing to solve normals "
                                "from misaligned scans — rescan this face")
    return Registration(M, angle_deg, float(corr), residual)


def register_scans(scans: list, dpi: float, *, nominal_deg: list | None = None, masks: list | None = None,
                   progress=None, **kw) -> list[Registration]:
    """Register every scan to the first (the target scan); the first gets the identity.

    ``nominal_deg`` are the nominal rotations of the scans (e.g. 0, 90, 180, 270); scan i is
    searched around the measured angle of scan i−1 plus the nominal step, since a person's
    errors in turning the fragment accumulate.
    """
    if len(scans) < 1:
        raise ValueError("scans must not be empty")
    masks = masks or [fragment_mask(s, dpi) for s in scans]
    out = [Registration(np.array([[1.0, 0, 0], [0, 1.0, 0]]), 0.0, 1.0, 0.0)]
    for i in range(1, len(scans)):
        # each turn is ~90° ± 10°, so errors add up: expect this scan relative to the previous
        # scan's measured angle rather than to the nominal angle alone
        nom = None if nominal_deg is None else out[-1].angle_deg + nominal_deg[i] - nominal_deg[i - 1]
        try:
            out.append(register_scan(scans[0], scans[i], dpi, nominal_deg=nom, target_mask=masks[0],
                                     moving_mask=masks[i], **kw))
        except RegistrationError as exc:
            raise RegistrationError(f"scan {i} (nominal {nom}°): {exc}") from exc
        if progress:
            progress(i / max(1, len(scans) - 1), f"registered scan {i}")
    return out


def warp_to_target(scan: np.ndarray, reg: Registration, shape: tuple[int, int]) -> np.ndarray:
    """Resample a scan (any dtype) into the target scan's frame (float32, full scale 1)."""
    img = to_float(scan)
    return cv2.warpAffine(img, reg.affine, (shape[1], shape[0]), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
