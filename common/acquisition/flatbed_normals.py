"""Normals and albedo from four rotated flatbed scans: photometric stereo with a linear lamp (§3.3.6).

The calibrated lamp model (eq. 3.4) gives the reading of a surface with albedo ρ and normal n
in the scanner's frame as ``I = ρ a · (n_x, n_y, n_z, 1)``. In scan i the fragment is rotated by
R_i relative to the target scan, so its normal there is R_i n and (eq. 3.5)

    I_i = ρ a · (R_i n, 1) = ρ (R_i⁻¹ a) · (n, 1),

i.e. the inverse rotation acts on a. R_i turns about z, so the n_z and constant columns of the
stacked system are the same in every row and the 4-column matrix is singular; dropping the
constant column by folding it into the z unknown gives the 3-unknown system (eq. 3.6)

    Ã (ρ n_x, ρ n_y, ρ ñ_z)ᵀ = I,   Ã_i = ((R_i⁻¹ a)_x, (R_i⁻¹ a)_y, a_z),   ñ_z = n_z + a_w / a_z,

solved per pixel by least squares. ρ and n follow from |n| = 1 (eq. 3.7): with
(u, v, w) the solution and c = a_w / a_z, ρ is the positive root of
``(1 − c²) ρ² + 2 c w ρ − (u² + v² + w²) = 0`` and n = (u/ρ, v/ρ, w/ρ − c).

Per pixel, samples that are saturated, outside the registered scan, or shadowed (the darkest
sample when the four disagree beyond the noise) are dropped and the rest re-solved; the
confidence map records how many samples were used and how well they agreed. The RGB albedo is
the least-squares scale of each channel given the solved shading.

Notes
-----
The thesis' ``a = (a_x, a_y, a_z, a_w)`` are ``a[0..3]`` here; angles are clockwise on the image
(the operator's "turn 90° clockwise"), converted to the y-up normal frame in :func:`light_rows`.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from common.acquisition.errors import CalibrationError
from common.acquisition.locate import fragment_mask, to_float
from common.acquisition.registration import Registration, register_scans, warp_to_target
from common.rgbn.image import RGBNImage


def light_rows(a: np.ndarray, angles_deg: Sequence[float]) -> np.ndarray:
    """Rows of Ã (eq. 3.6): ((R_i⁻¹ a)_x, (R_i⁻¹ a)_y, a_z) for each scan's rotation.

    Parameters
    ----------
    a : (4,) array
        Lamp model coefficients (eq. 3.4).
    angles_deg : sequence of float
        Rotation of the fragment in each scan relative to the target scan, clockwise on the
        image (y down), as estimated by registration.

    Returns
    -------
    (K, 3) array
    """
    a = np.asarray(a, float)
    if a.shape != (4,):
        raise ValueError(f"a must have 4 coefficients, got shape {a.shape}")
    rows = []
    for ang in angles_deg:
        t = np.deg2rad(ang)
        # clockwise on a y-down image is counter-clockwise by -t... in the y-up frame: R = F Q F
        R = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
        bxy = R.T @ a[:2]                      # R_i^-1 a (rotations: inverse = transpose)
        rows.append([bxy[0], bxy[1], a[2]])
    return np.array(rows)


def _solve_patterns(Y: np.ndarray, use: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares per pixel with a per-pixel subset of rows; pixels grouped by subset."""
    K, N = Y.shape
    code = np.zeros(N, np.int64)
    for k in range(K):
        code |= use[k].astype(np.int64) << k
    x = np.zeros((3, N), np.float32)
    solved = np.zeros(N, bool)
    for c in np.unique(code):
        rows = [k for k in range(K) if c >> k & 1]
        if len(rows) < 3:
            continue
        sel = code == c
        P = np.linalg.pinv(A[rows]).astype(np.float32)
        x[:, sel] = P @ Y[rows][:, sel]
        solved[sel] = True
    return x, solved


def _recover(x: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """ρ and unit n from (ρ n_x, ρ n_y, ρ ñ_z) with ñ_z = n_z + c (eq. 3.7)."""
    u, v, w = x
    q = u * u + v * v + w * w
    one = 1.0 - c * c
    if abs(one) > 1e-9:
        disc = np.maximum(w * w * c * c + one * q, 0)
        rho = (-w * c + np.sqrt(disc)) / one
    else:
        rho = q / np.maximum(2 * w * c, 1e-12)
    rho = np.maximum(rho, 1e-9)
    n = np.stack([u / rho, v / rho, w / rho - c])
    n[2] = np.maximum(n[2], 0.0)           # a visible face looks towards the sensor
    n /= np.maximum(np.linalg.norm(n, axis=0), 1e-12)
    return rho, n


def solve_normals(images: np.ndarray, angles_deg: Sequence[float], a: np.ndarray, *, mask: np.ndarray | None = None,
                  valid: np.ndarray | None = None, saturation: float = 0.98, k_sigma: float = 4.0,
                  dpi: float = 600.0) -> RGBNImage:
    """Photometric stereo for the flatbed (eqs. 3.4–3.7): RGB albedo, unit normals, confidence.

    Parameters
    ----------
    images : (K, H, W, 3) float array
        Scans registered to the target scan's frame, full scale 1, K >= 3 (4 in the thesis).
    angles_deg : (K,) sequence
        Rotation of the fragment in each scan relative to the target scan (clockwise on the image).
    a : (4,) array
        Calibrated lamp coefficients of eq. 3.4 (for albedo 1).
    mask : (H, W) bool or None
        Fragment mask (None = all pixels).
    valid : (K, H, W) bool or None
        False where a scan has no data (outside its registered footprint).
    saturation : float
        Samples with any channel at or above this fraction of full scale are dropped.
    k_sigma : float
        Samples disagreeing by more than ``k_sigma`` robust standard deviations (estimated from
        the data) trigger shadow rejection.
    dpi : float
        Resolution, recorded in the result.

    Returns
    -------
    RGBNImage
        ``albedo`` (reflectance, calibration target units), ``normals`` (x right, y up, z to the
        viewer), ``confidence`` in [0, 1], ``mask``; ``attrs['samples_used_mean']``.
    """
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[3] != 3:
        raise ValueError(f"images must be (K, H, W, 3), got {images.shape}")
    K, H, W, _ = images.shape
    if K < 3:
        raise ValueError(f"need at least 3 registered scans, got {K}")
    if len(angles_deg) != K:
        raise ValueError(f"angles_deg must have {K} entries, got {len(angles_deg)}")
    a = np.asarray(a, float)
    if a.shape != (4,) or not a[2] > 0:
        raise CalibrationError(f"lamp coefficients a must be 4 numbers with a_z > 0, got {a}")
    if mask is None:
        mask = np.ones((H, W), bool)
    mask = np.asarray(mask, bool)
    if mask.shape != (H, W):
        raise ValueError(f"mask must be {(H, W)}, got {mask.shape}")
    A = light_rows(a, angles_deg)
    c = a[3] / a[2]
    idx = np.flatnonzero(mask.ravel())
    pix = images.reshape(K, H * W, 3)[:, idx]                  # (K, N, 3)
    Y = pix.mean(axis=2)                                        # luminance (K, N)
    use = pix.max(axis=2) < saturation
    if valid is not None:
        use &= np.asarray(valid, bool).reshape(K, H * W)[:, idx]
    x, solved = _solve_patterns(Y, use, A)
    # shadow rejection where all samples were usable and disagree beyond the noise
    full = use.all(axis=0) & solved
    resid = Y - (A.astype(np.float32) @ x)
    if K > 3 and full.any():
        rn = np.sqrt((resid[:, full] ** 2).sum(axis=0))
        sigma = 1.4826 * np.median(np.abs(rn - np.median(rn))) + np.median(rn) * 0.5 + 1e-6
        bad = np.zeros(len(idx), bool)
        bad[full] = rn > k_sigma * sigma + 0.01 * Y[:, full].mean(axis=0)
        if bad.any():
            r = resid[:, bad]
            neg = r < -0.5 * np.abs(r).max(axis=0)
            darkness = np.where(neg, Y[:, bad], np.inf)
            drop = np.argmin(darkness, axis=0)
            use2 = use[:, bad].copy()
            use2[drop, np.arange(bad.sum())] = False
            x2, ok2 = _solve_patterns(Y[:, bad], use2, A)
            xb = x[:, bad]
            xb[:, ok2] = x2[:, ok2]
            x[:, bad] = xb
            ub = use[:, bad]
            ub[:, ok2] = use2[:, ok2]
            use[:, bad] = ub
        sig_full = sigma
    else:
        sig_full = None
    rho, n = _recover(x, c)
    # shading of each sample and RGB albedo by least squares over the used samples
    shading = (A @ np.vstack([n[0], n[1], n[2] + c])).astype(np.float32)       # (K, N)
    wts = use & (shading > 1e-4)
    num = np.einsum("kn,knc->nc", np.where(wts, shading, 0), pix)
    den = np.maximum((np.where(wts, shading, 0) ** 2).sum(axis=0), 1e-9)
    albedo = np.clip(num / den[:, None], 0, 1)
    nused = use.sum(axis=0)
    conf = np.clip((nused - 2) / (K - 2), 0, 1).astype(np.float32)
    conf[~solved] = 0
    if sig_full is not None:
        r_final = (Y - shading * rho) * use
        rn = np.sqrt((r_final ** 2).sum(axis=0))
        conf *= np.exp(-0.5 * (rn / (k_sigma * sig_full + 1e-6)) ** 2).astype(np.float32)
    # outputs
    normals = np.zeros((H * W, 3), np.float32)
    normals[:, 2] = 1
    normals[idx] = np.where(solved[:, None], n.T, (0, 0, 1))
    alb = np.zeros((H * W, 3), np.float32)
    alb[idx] = albedo
    cmap = np.zeros(H * W, np.float32)
    cmap[idx] = conf
    out_mask = np.zeros(H * W, bool)
    out_mask[idx] = solved
    return RGBNImage(albedo=alb.reshape(H, W, 3), mask=out_mask.reshape(H, W), dpi=dpi,
                     normals=normals.reshape(H, W, 3), confidence=cmap.reshape(H, W),
                     attrs={"samples_used_mean": float(nused.mean()) if len(idx) else 0.0})


def rerender(image: RGBNImage, angles_deg: Sequence[float], a: np.ndarray) -> np.ndarray:
    """Predict each scan (K, H, W, 3) from albedo and normals under the calibrated light (eq. 3.5)."""
    A = light_rows(a, angles_deg)
    c = np.asarray(a, float)[3] / np.asarray(a, float)[2]
    n = image.normals.reshape(-1, 3).T
    s = A @ np.vstack([n[0], n[1], n[2] + c])
    H, W = image.shape
    return (s.reshape(len(A), H, W, 1) * image.albedo[None]).astype(np.float32)


def rerender_residual(image: RGBNImage, registered: np.ndarray, angles_deg, a, *, valid=None) -> float:
    """RMS of (scan − prediction) inside the mask relative to the mean scan value (fraction)."""
    pred = rerender(image, angles_deg, a)
    m = image.mask[None, ..., None] & np.ones_like(pred, bool)
    if valid is not None:
        m &= np.asarray(valid, bool)[..., None]
    m &= registered < 0.98
    d = (registered - pred)[m]
    return float(np.sqrt(np.mean(d ** 2)) / max(np.mean(registered[m]), 1e-9))


def solve_face(scans: Sequence[np.ndarray], dpi: float, a: np.ndarray, *, nominal_deg: Sequence[float] | None = None,
               progress: Callable[[float, str], None] | None = None, **kw) -> tuple[RGBNImage, list[Registration]]:
    """Register the scans of one face to the first and solve its RGBN image (§3.3.6).

    Returns the RGBN image in the target scan's frame and the registrations (with residuals).
    """
    if len(scans) < 3:
        raise ValueError(f"need at least 3 scans of a face for normals, got {len(scans)}")
    masks = [fragment_mask(s, dpi) for s in scans]
    regs = register_scans(list(scans), dpi, nominal_deg=nominal_deg, masks=masks,
                          progress=(lambda f, t: progress(0.6 * f, t)) if progress else None)
    H, W = scans[0].shape[:2]
    images = np.empty((len(scans), H, W, 3), np.float32)
    valid = np.empty((len(scans), H, W), bool)
    import cv2
    for i, (s, r) in enumerate(zip(scans, regs)):
        images[i] = to_float(s) if i == 0 else warp_to_target(s, r, (H, W))
        ones = np.ones(s.shape[:2], np.uint8)
        valid[i] = cv2.warpAffine(ones, r.affine, (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0 if i else True
    if progress:
        progress(0.7, "solving normals")
    out = solve_normals(images, [r.angle_deg for r in regs], a, mask=masks[0], valid=valid, dpi=dpi, **kw)
    out.attrs["registration_residual"] = float(max(r.residual for r in regs))
    out.attrs["registration_correlation_min"] = float(min(r.correlation for r in regs))
    if progress:
        progress(1.0, "solved")
    return out, regs


def colour_only_face(scan: np.ndarray, dpi: float, a: np.ndarray) -> RGBNImage:
    """Albedo of a colour-only scan: reading divided by the model's flat-surface response a_z + a_w."""
    a = np.asarray(a, float)
    img = to_float(scan)
    return RGBNImage(albedo=np.clip(img / (a[2] + a[3]), 0, 1), mask=fragment_mask(scan, dpi), dpi=dpi)
