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

import cv2
import numpy as np

from common.acquisition.errors import CalibrationError
from common.acquisition.locate import face_masks, fragment_mask, to_float
from common.acquisition.registration import Registration, register_scans
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
    """Least squares per pixel with a per-pixel subset of rows; pixels grouped by subset.

    Each subset (at most 2^K) is one pseudo-inverse applied to all its pixels at once; the
    common case, every sample usable, is a single (3, K) @ (K, N) product.
    """
    K, N = Y.shape
    code = np.zeros(N, np.uint8 if K <= 8 else np.int64)
    for k in range(K):
        code |= use[k].astype(code.dtype) << k
    everything = (1 << K) - 1
    x = np.zeros((3, N), np.float32)
    solved = np.zeros(N, bool)
    counts = np.bincount(code, minlength=1 << K) if K <= 16 else None
    present = np.flatnonzero(counts) if counts is not None else np.unique(code)
    present = sorted(present, key=lambda c: c != everything)      # the all-samples group first
    for c in present:
        rows = [k for k in range(K) if c >> k & 1]
        if len(rows) < 3:
            continue
        P = np.linalg.pinv(A[rows]).astype(np.float32)
        if c == everything and counts is not None and counts[c] > N // 2:
            x = P @ Y                               # most pixels: all at once, others overwritten
            solved |= code == c
            continue
        sel = code == c
        x[:, sel] = P @ Y[rows][:, sel]
        solved[sel] = True
    if counts is not None and counts[everything] > N // 2:
        x[:, ~solved] = 0
    return x.astype(np.float32, copy=False), solved


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
    inv = 1 / rho
    n = np.stack([u * inv, v * inv, np.maximum(w * inv - c, 0)])   # a visible face looks towards the sensor
    n *= 1 / np.maximum(np.sqrt((n * n).sum(axis=0)), 1e-12)
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
    idx = np.flatnonzero(mask.ravel())
    pix = images.reshape(K, H * W, 3)[:, idx]                  # (K, N, 3)
    use = None if valid is None else np.asarray(valid, bool).reshape(K, H * W)[:, idx]
    return _solve_samples(pix, use, (H, W), idx, angles_deg, a, saturation=saturation, k_sigma=k_sigma, dpi=dpi)


_CHUNK = 1 << 17      # pixels per block: the per-pixel work stays in the CPU cache


def _first_pass(pix, valid, A, saturation):
    Y = (pix[..., 0] + pix[..., 1] + pix[..., 2]) * np.float32(1 / 3)   # luminance (K, N)
    use = (pix[..., 0] < saturation) & (pix[..., 1] < saturation) & (pix[..., 2] < saturation)
    if valid is not None:
        use &= valid
    x, solved = _solve_patterns(Y, use, A)
    resid = Y - A @ x
    return Y, use, x, solved, resid


def _solve_block(pix, valid, A, c, saturation, k_sigma, sigma):
    """Solve one block of pixels; returns albedo (N, 3), normals (3, N), confidence, solved, used."""
    K = pix.shape[0]
    Y, use, x, solved, resid = _first_pass(pix, valid, A, saturation)
    full = use.all(axis=0) & solved
    if sigma is not None:
        # shadow rejection where all samples were usable and disagree beyond the noise
        rn_all = np.sqrt((resid * resid).sum(axis=0))
        bad = full & (rn_all > k_sigma * sigma + 0.01 * Y.mean(axis=0))
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
    rho, n = _recover(x, c)
    # shading of each sample and RGB albedo by least squares over the used samples
    shading = A @ np.stack([n[0], n[1], n[2] + c])                               # (K, N)
    ws = np.where(use & (shading > 1e-4), shading, np.float32(0))
    num = np.stack([(ws * pix[..., ch]).sum(axis=0) for ch in range(3)], axis=1)
    den = np.maximum((ws * ws).sum(axis=0), 1e-9)
    albedo = np.clip(num / den[:, None], 0, 1)
    nused = use.sum(axis=0)
    conf = np.clip((nused - 2) / (K - 2), 0, 1).astype(np.float32)
    conf[~solved] = 0
    if sigma is not None:
        r_final = (Y - shading * rho) * use
        rn = np.sqrt((r_final * r_final).sum(axis=0))
        conf *= np.exp(-0.5 * (rn / (k_sigma * sigma + 1e-6)) ** 2).astype(np.float32)
    return albedo, n, conf, solved, nused


def _lamp_groups(a, n: int):
    """Distinct lamp models among the samples: a (4,) for all, or (N, 4) one per sample.

    Returns a list of (a_k (4,), selection) with selection a slice or an index array."""
    a = np.asarray(a, float)
    if a.ndim == 1:
        return [(a, slice(None))]
    if a.shape != (n, 4):
        raise ValueError(f"per-sample lamp coefficients must be ({n}, 4), got {a.shape}")
    rows, inv = np.unique(a, axis=0, return_inverse=True)
    inv = inv.ravel()
    return [(rows[k], np.flatnonzero(inv == k)) for k in range(len(rows))]


def _solve_samples(pix: np.ndarray, valid: np.ndarray | None, shape, idx, angles_deg, a, *, saturation: float,
                   k_sigma: float, dpi: float) -> RGBNImage:
    """The solve on gathered samples: ``pix`` (K, N, 3) float32 at the flat pixel indices ``idx``.

    ``a`` is the lamp model (4,), or one per sample (N, 4) (a lamp that changes with the distance
    from the glass, :func:`solve_face`); samples sharing a model are solved together."""
    K, N = pix.shape[:2]
    H, W = shape
    groups = _lamp_groups(a, N)
    for ak, _ in groups:
        if not (ak.shape == (4,) and ak[2] > 0):
            raise CalibrationError(f"lamp coefficients a must be 4 numbers with a_z > 0, got {ak}")
    # the noise level for shadow rejection, from a subsample of pixels with every sample usable
    # (under the model most samples share)
    sizes = [N if isinstance(g, slice) else len(g) for _, g in groups]
    a_main = groups[int(np.argmax(sizes))][0]
    sigma = None
    if K > 3 and N:
        A = light_rows(a_main, angles_deg).astype(np.float32)
        sub = slice(None, None, max(1, N // 200_000))
        Y, use, x, solved, resid = _first_pass(pix[:, sub], None if valid is None else valid[:, sub], A, saturation)
        full = use.all(axis=0) & solved
        if full.any():
            rn = np.sqrt((resid[:, full] ** 2).sum(axis=0))
            med = np.median(rn)
            sigma = float(1.4826 * np.median(np.abs(rn - med)) + med * 0.5 + 1e-6)
    normals = np.zeros((H * W, 3), np.float32)
    normals[:, 2] = 1
    alb = np.zeros((H * W, 3), np.float32)
    cmap = np.zeros(H * W, np.float32)
    out_mask = np.zeros(H * W, bool)
    used_total = 0
    for ak, gsel in groups:
        A = light_rows(ak, angles_deg).astype(np.float32)
        c = np.float32(ak[3] / ak[2])
        gidx = np.arange(N)[gsel]
        for s0 in range(0, len(gidx), _CHUNK):
            blk = gidx[s0:s0 + _CHUNK]
            if len(groups) == 1:
                blk = slice(s0, min(N, s0 + _CHUNK))
            albedo, n, conf, solved, nused = _solve_block(pix[:, blk], None if valid is None else valid[:, blk], A, c,
                                                          saturation, k_sigma, sigma)
            ii = idx[blk]
            normals[ii] = np.where(solved[:, None], n.T, np.float32([0, 0, 1]))
            alb[ii] = albedo
            cmap[ii] = conf
            out_mask[ii] = solved
            used_total += int(nused.sum())
    return RGBNImage(albedo=alb.reshape(H, W, 3), mask=out_mask.reshape(H, W), dpi=dpi,
                     normals=normals.reshape(H, W, 3), confidence=cmap.reshape(H, W),
                     attrs={"samples_used_mean": used_total / N if N else 0.0,
                            "noise_sigma": float(sigma) if sigma is not None else float("nan")})


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


def rerender_residuals_at(image: RGBNImage, pix: np.ndarray, valid: np.ndarray, idx: np.ndarray, angles_deg,
                          a: np.ndarray, *, saturation: float = 0.98) -> list[float]:
    """Re-rendering residual of each scan, from the scans' samples at the solved pixels.

    As :func:`rerender_residual` (RMS of scan − prediction over the mean scan value, saturated and
    unregistered samples left out) but per scan and without whole-frame arrays.

    Parameters
    ----------
    image : RGBNImage
        The solved face.
    pix : (K, N, 3) float
        Each scan's RGB at the pixels ``idx`` (flat indices into the face), full scale 1.
    valid : (K, N) bool
        Samples inside the registered scan.
    idx : (N,) int
    angles_deg
        As :func:`rerender`.
    a : (4,) or (N, 4) float
        The lamp model, or one per pixel (:func:`solve_face` with a depth-dependent lamp).

    Returns
    -------
    list of K floats (NaN for a scan with no solved sample).
    """
    n = image.normals.reshape(-1, 3)[idx].astype(np.float32)
    alb = image.albedo.reshape(-1, 3)[idx].astype(np.float32)
    solved = image.mask.reshape(-1)[idx]
    K = pix.shape[0]
    shading = np.zeros((K, len(idx)), np.float32)
    for ak, g in _lamp_groups(a, len(idx)):
        A = light_rows(ak, angles_deg)
        c = float(ak[3] / ak[2])
        shading[:, g] = (A[:, :1] * n[g, 0] + A[:, 1:2] * n[g, 1] + A[:, 2:3] * (n[g, 2] + c))
    out = []
    for k in range(K):
        p = pix[k]
        # channel by channel: numpy's reductions over a length-3 axis are slow on millions of pixels
        unsat = (p[:, 0] < saturation) & (p[:, 1] < saturation) & (p[:, 2] < saturation)
        usef = (solved & valid[k] & unsat).astype(np.float32)
        n_use = float(usef.sum())
        if n_use == 0:
            out.append(float("nan"))
            continue
        sq = np.zeros(len(idx), np.float32)
        for ch in range(3):
            d = p[:, ch] - shading[k] * alb[:, ch]
            sq += d * d
        ss = float(usef @ sq)
        so = float(usef @ (p[:, 0] + p[:, 1] + p[:, 2]))
        out.append(float(np.sqrt(ss / (3 * n_use)) / max(so / (3 * n_use), 1e-9)))
    return out


def register_face(scans: Sequence[np.ndarray], dpi: float, *, turn: str | None = None,
                  nominal_deg: Sequence[float] | None = None, progress=None, min_consistency: float = 0.9):
    """Masks, registration and the fragment's consistent mask for the turned scans of one face.

    Masks by colour, or by focus where the colour masks disagree in area
    (:func:`~common.acquisition.locate.face_masks`); registration with the given turn direction
    (:func:`~common.acquisition.registration.register_turned`) or nominal rotations
    (:func:`~common.acquisition.registration.register_scans`); then :func:`consistent_mask`. When
    the colour masks register but less than ``min_consistency`` of the target's mask is seen by
    every scan — they hold something that does not turn with the fragment, a shadow as grey as the
    bed beside a fragment of the bed's grey — the focus masks are tried and kept if more of them
    is consistent; when the colour masks do not register at all, the focus masks are tried before
    the registration error is raised.

    Returns
    -------
    turn : str or None
        The direction used (with ``turn``), else None.
    regs : list of Registration
    mask : (H, W) bool
        The consistent mask in the target scan's frame.
    method : {"colour", "focus"}
    """
    from common.acquisition.errors import RegistrationError
    from common.acquisition.locate import focus_mask
    from common.acquisition.registration import register_turned

    shape = np.asarray(scans[0]).shape[:2]

    def reg(masks):
        if turn is not None:
            return register_turned(list(scans), dpi, turn, masks=masks, progress=progress)
        return None, register_scans(list(scans), dpi, nominal_deg=nominal_deg, masks=masks, progress=progress)

    masks, method = face_masks(list(scans), dpi)
    try:
        used, regs = reg(masks)
    except RegistrationError as exc:
        if method != "colour":
            raise
        focus = [focus_mask(s, dpi) for s in scans]
        try:                    # the colour masks may hold what does not turn (a shadow): try focus
            used, regs = reg(focus)
        except RegistrationError:
            raise exc from None
        return used, regs, consistent_mask(focus, regs, shape), "focus"
    mask = consistent_mask(masks, regs, shape)
    share = mask.sum() / max(1, np.count_nonzero(masks[0]))
    if method == "colour" and share < min_consistency:
        focus = [focus_mask(s, dpi) for s in scans]
        try:
            used2, regs2 = reg(focus)
        except RegistrationError:
            return used, regs, mask, method
        mask2 = consistent_mask(focus, regs2, shape)
        if mask2.sum() / max(1, np.count_nonzero(focus[0])) > share:
            return used2, regs2, mask2, "focus"
    return used, regs, mask, method


def consistent_mask(masks: Sequence[np.ndarray], regs: Sequence[Registration], shape: tuple[int, int]) -> np.ndarray:
    """The fragment where every registered scan sees it: the target's mask ∩ the others' warped back.

    What turns with the fragment lands on the same pixels once the scans are registered; what
    stays with the scanner — the lamp's shadow beside the fragment, always on the lamp's far side,
    or a patch of the bed the mask took — lands elsewhere in each and drops out. Pixels a scan does
    not cover (outside its frame) are not constrained by it. The largest region is kept, holes
    filled.

    Parameters
    ----------
    masks : sequence of (H_i, W_i) bool
        Each scan's fragment mask, in its own frame.
    regs : sequence of Registration
        Target-to-scan maps (``regs[0]`` the identity).
    shape : (H, W)
        The target scan's size.

    Returns
    -------
    (H, W) bool
    """
    from common.acquisition.locate import _fill_holes

    H, W = shape
    out = np.asarray(masks[0], bool).copy()
    for m, r in zip(masks[1:], regs[1:]):
        w = cv2.warpAffine(np.asarray(m, np.uint8), r.affine, (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=1)
        out &= w > 0
    n, lab, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
    if n < 2:
        return out
    return _fill_holes(lab == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])))


def face_depth_map(normals: np.ndarray, mask: np.ndarray, pixel_mm: float, *, grid_mm: float = 0.25) -> np.ndarray:
    """Distance of each fragment pixel from the glass (mm), from its solved normals.

    The normals' slopes (h_x = −n_x/n_z, h_y = −n_y/n_z, y up) are averaged on a ``grid_mm`` grid
    and integrated by least squares (the discrete Poisson problem of surface-from-gradient,
    e.g. Agrawal, Raskar & Chellappa, ECCV 2006, §2), each connected region on its own; a fragment
    rests on its highest points, so a region's distance from the glass is its highest height minus
    the height. The result is interpolated back to the pixels.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals (x right, y up, z to the sensor).
    mask : (H, W) bool
        Solved fragment pixels.
    pixel_mm : float
        Pixel size, mm.
    grid_mm : float
        Integration grid (the lamp's change with distance is ~1–2 % per mm, so the relief finer
        than this does not matter to it).

    Returns
    -------
    (H, W) float32
        Distance from the glass in mm on ``mask``, NaN elsewhere.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    H, W = mask.shape
    out = np.full((H, W), np.nan, np.float32)
    if not mask.any():
        return out
    k = max(1, int(round(grid_mm / pixel_mm)))
    h2, w2 = -(-H // k), -(-W // k)
    m = np.zeros((h2 * k, w2 * k), np.float32)
    m[:H, :W] = mask
    nz = np.clip(normals[..., 2].astype(np.float64), 0.2, None)
    gx = np.zeros_like(m, np.float64)
    gy = np.zeros_like(m, np.float64)
    gx[:H, :W] = np.where(mask, -normals[..., 0] / nz, 0)        # dh/dx, x right
    gy[:H, :W] = np.where(mask, normals[..., 1] / nz, 0)         # dh/drow, rows down (y up)

    def pool(a):
        return a.reshape(h2, k, w2, k).sum(axis=(1, 3))
    cnt = pool(m)
    mg = cnt > 0.5 * k * k
    gx = pool(gx) / np.maximum(cnt, 1)
    gy = pool(gy) / np.maximum(cnt, 1)
    step = k * pixel_mm
    ncomp, lab = cv2.connectedComponents(mg.astype(np.uint8), connectivity=4)
    hgrid = np.full((h2, w2), np.nan)
    ids = -np.ones((h2, w2), np.int64)
    ids[mg] = np.arange(int(mg.sum()))
    rows, cols, vals, rhs = [], [], [], []
    ys, xs = np.nonzero(mg[:, :-1] & mg[:, 1:])
    eq = np.arange(len(ys))
    rows += [eq, eq]
    cols += [ids[ys, xs], ids[ys, xs + 1]]
    vals += [-np.ones(len(ys)), np.ones(len(ys))]
    rhs.append((gx[ys, xs] + gx[ys, xs + 1]) / 2 * step)
    base = len(ys)
    ys, xs = np.nonzero(mg[:-1, :] & mg[1:, :])
    eq = base + np.arange(len(ys))
    rows += [eq, eq]
    cols += [ids[ys, xs], ids[ys + 1, xs]]
    vals += [-np.ones(len(ys)), np.ones(len(ys))]
    rhs.append((gy[ys, xs] + gy[ys + 1, xs]) / 2 * step)
    n_eq, n_un = base + len(ys), int(mg.sum())
    # one anchor per region (its first cell at height 0) makes the system non-singular
    _, at = np.unique(lab[mg], return_index=True)         # labels 1..ncomp-1 in order; their first cells
    first = np.asarray(at, np.int64)
    eq = n_eq + np.arange(len(first))
    rows.append(eq)
    cols.append(first)
    vals.append(np.ones(len(first)))
    rhs.append(np.zeros(len(first)))
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_eq + len(first), n_un))
    h = spl.spsolve((A.T @ A).tocsc(), A.T @ np.concatenate(rhs))
    hgrid[mg] = h
    top = np.full(ncomp, -np.inf)
    np.maximum.at(top, lab[mg], hgrid[mg])                # each region's highest point rests on the glass
    dist = np.full((h2, w2), np.nan)
    dist[mg] = top[lab[mg]] - hgrid[mg]
    # back to the pixels: bilinear on the grid's cell centres, holes filled from the nearest cell
    fill = np.where(mg, dist, 0.0).astype(np.float32)
    wgt = mg.astype(np.float32)
    up = cv2.resize(fill, (w2 * k, h2 * k), interpolation=cv2.INTER_LINEAR)[:H, :W]
    uw = cv2.resize(wgt, (w2 * k, h2 * k), interpolation=cv2.INTER_LINEAR)[:H, :W]
    from scipy.ndimage import distance_transform_edt
    iy, ix = distance_transform_edt(~mg, return_distances=False, return_indices=True)   # nearest integrated cell
    near = cv2.resize(dist[iy, ix].astype(np.float32), (w2 * k, h2 * k), interpolation=cv2.INTER_NEAREST)[:H, :W]
    d = np.where(uw > 0.25, up / np.maximum(uw, 1e-6), near)
    out[mask] = d[mask]
    return out


def _sample_rgb(image: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 3) of an (H, W, 3) image at points q = (x, y) (2, N)."""
    n = q.shape[1]
    rows = -(-n // 1024)
    mx = np.full(rows * 1024, -1e6, np.float32)
    my = np.full(rows * 1024, -1e6, np.float32)
    mx[:n], my[:n] = q[0], q[1]
    out = cv2.remap(image, mx.reshape(rows, 1024), my.reshape(rows, 1024), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(-1, 3)[:n]


def solve_face(scans: Sequence[np.ndarray], dpi: float, a: np.ndarray, *, nominal_deg: Sequence[float] | None = None,
               progress: Callable[[float, str], None] | None = None, a_per_mm: np.ndarray | None = None,
               a_depth_mm: float = 0.0, depth_step_mm: float = 0.05, max_depth_mm: float = 3.0,
               **kw) -> tuple[RGBNImage, list[Registration]]:
    """Register the scans of one face to the first and solve its RGBN image (§3.3.6).

    With ``a_per_mm`` (the calibration's change of the lamp model per mm of distance from the
    glass, :func:`~common.acquisition.calibration.fit_target_readings`) the face is solved twice:
    once with ``a`` (read at ``a_depth_mm``), then each pixel again with the model at its own
    distance from the glass, ``a + (d − a_depth_mm) a_per_mm``, d from the first solve's normals
    (:func:`face_depth_map`), rounded to ``depth_step_mm`` and clipped to [0, ``max_depth_mm``]
    (beyond what targets a few millimetres high measured, the model is not extrapolated). A
    fragment rests on its highest points, and the rest of its face lies up to a millimetre or more
    behind them, where a flatbed lamp is 1–2 % dimmer than at the glass.

    Returns the RGBN image in the target scan's frame and the registrations (with residuals).
    """
    if len(scans) < 3:
        raise ValueError(f"need at least 3 scans of a face for normals, got {len(scans)}")
    H, W = scans[0].shape[:2]
    _, regs, mask, method = register_face(list(scans), dpi, nominal_deg=nominal_deg,
                                          progress=(lambda f, t: progress(0.6 * f, t)) if progress else None)
    idx = np.flatnonzero(mask.ravel())
    ys, xs = np.divmod(idx, W)
    xs, ys = xs.astype(np.float32), ys.astype(np.float32)
    K = len(scans)
    pix = np.empty((K, len(idx), 3), np.float32)
    valid = np.ones((K, len(idx)), bool)
    for i, (s, r) in enumerate(zip(scans, regs)):
        # sample each scan only at the target's fragment pixels (no full-frame warps)
        s = np.asarray(s)
        scale = np.float32(1 / 65535 if s.dtype == np.uint16 else 1 / 255 if s.dtype == np.uint8 else 1)
        if i == 0:
            pix[0] = s.reshape(-1, s.shape[2])[idx, :3] * scale
            continue
        m = r.affine.astype(np.float32)
        q = np.stack([m[0, 0] * xs + m[0, 1] * ys + m[0, 2], m[1, 0] * xs + m[1, 1] * ys + m[1, 2]])
        pix[i] = _sample_rgb(np.ascontiguousarray(s[..., :3]), q) * scale
        valid[i] = (q[0] >= 0) & (q[1] >= 0) & (q[0] <= s.shape[1] - 1) & (q[1] <= s.shape[0] - 1)
    if progress:
        progress(0.7, "solving normals")
    angles = [r.angle_deg for r in regs]
    a = np.asarray(a, float)
    out = _solve_samples(pix, valid, (H, W), idx, angles, a,
                         saturation=kw.get("saturation", 0.98), k_sigma=kw.get("k_sigma", 4.0), dpi=dpi)
    a_used = a
    if a_per_mm is not None and np.any(np.asarray(a_per_mm, float) != 0) and out.mask.any():
        if progress:
            progress(0.85, "lamp at each pixel's distance from the glass")
        depth = face_depth_map(out.normals, out.mask, 25.4 / dpi).reshape(-1)[idx]
        depth = np.where(np.isfinite(depth), depth, a_depth_mm)
        depth = np.clip(np.round(depth / depth_step_mm) * depth_step_mm, 0.0, max_depth_mm)
        a_used = a[None, :] + (depth[:, None] - a_depth_mm) * np.asarray(a_per_mm, float)[None, :]
        out = _solve_samples(pix, valid, (H, W), idx, angles, a_used,
                             saturation=kw.get("saturation", 0.98), k_sigma=kw.get("k_sigma", 4.0), dpi=dpi)
        out.attrs["face_depth_mm_median"] = float(np.median(depth))
        out.attrs["face_depth_mm_p95"] = float(np.percentile(depth, 95))
    per_scan = rerender_residuals_at(out, pix, valid, idx, angles, a_used, saturation=kw.get("saturation", 0.98))
    out.attrs["mask_method"] = method
    out.attrs["rerender_residual_per_scan"] = [round(float(v), 5) for v in per_scan]
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
