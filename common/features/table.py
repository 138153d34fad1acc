"""The feature table of one fragment face: every descriptor of §5.4, per fragment and per patch.

:func:`extract_features` runs the whole extractor on an :class:`~common.rgbn.image.RGBNImage`;
:func:`save_features` / :func:`load_features` store tables as ``tessera.features`` artifacts (one
HDF5 group per face).

All pixel statistics run on a *working grid* of about 0.1 mm (the scan area-averaged by an
integer factor, fragment pixels only, weighted by how much of each grid cell is fragment). That
makes the descriptors independent of the scan dpi (a 600 and a 300 dpi scan of one fragment
describe it alike; detail finer than 0.1 mm is scanner noise for these cues) and fast: the
statistics that are functions of means (colour, normal-z, eq. 5.3) come from *moment channels*
(values, squares, products) stacked once, so a patch's statistic is one weighted sum over its disc.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Callable, Mapping

import cv2
import h5py
import numpy as np
from scipy import ndimage as ndi

from common.features.boundary import boundary_channel_names, boundary_profile
from common.features.colour import colour_channels, colour_from_moments
from common.features.contour import fragment_contour
from common.features.curvature import area_curvature, three_point_curvature
from common.features.erosion import _multiscale_erosion, erosion_statistics
from common.features.normal import (discontinuity_from_differences,
                                    neighbour_differences, normal_channels, normal_from_moments)
from common.features.orientation import dominant_orientation
from common.features.patches import MIN_COVERAGE, PATCH_SPACING_MM, disk_window, sample_patches
from common.features.registry import (CURVATURE_SCALES_MM, EROSION_SCALES, fragment_descriptors,
                                      patch_descriptors)
from common.rgbn.image import RGBNImage
from common.store import ArtifactError, ArtifactRef, Store

SCHEMA = "tessera.features"
SCHEMA_VERSION = 2  # 2: boundary profile (colour and thickness along the contour)
#: target pixel size of the working grid, mm (the actual one is an integer multiple of the scan's)
WORK_PIXEL_MM = 0.1
# fragment-level FFT runs on at most this many pixels per side, a patch's on at most that many
_FFT_MAX_PX = 512
_PATCH_FFT_PX = 128


@dataclass
class FeatureTable:
    """Descriptors of one fragment face.

    Attributes
    ----------
    values : dict name -> float
        Fragment-level descriptors (NaN = missing), names as in
        :func:`~common.features.registry.fragment_descriptors`.
    patch_names : list of str
        Column names of ``patch_values`` (:func:`~common.features.registry.patch_descriptors`).
    patch_values : (N, D) float
        Patch-level descriptors, one row per patch (NaN = missing).
    patch_centers_mm : (N, 2) patch centres, fragment frame (x = col * pixel_mm right, y = row *
        pixel_mm down)
    patch_normals : (N, 2) outward unit contour normal at the patch's contour point
    patch_arc_mm : (N,) arc position of that contour point from the contour start
    patch_kind : (N,) str, 'p10' (10 mm, 8 mm in) or 'p20' (20 mm, 13 mm in)
    patch_coverage : (N,) fraction of the patch disc on the fragment (below 0.6: values NaN,
        except the contour curvatures, which belong to the contour point)
    patch_contour_mm : (N, 2) the contour point of each patch
    contour_mm : (M, 2) the contour, uniformly sampled; contour_normals : (M, 2) outward normals
    boundary_names : list of str
        Columns of ``boundary_profile`` (:func:`~common.features.boundary.boundary_channel_names`).
    boundary_profile : (K, C) float
        Colour and thickness sampled along the contour every ``boundary_step_mm`` from its start,
        just inside it (:func:`~common.features.boundary.boundary_profile`); (0, 0) when absent
        (no contour, or a table written before schema version 2).
    boundary_step_mm : float
        Arc-length step of ``boundary_profile``, mm.
    dpi : float
        Scan dpi of the RGBN image.
    face : str
    fragment : str
        Fragment id ('' when not known, e.g. a table of a loose RGBN file).
    work_pixel_mm : float
        Pixel size of the working grid the pixel statistics ran on.
    missing_data : list of str
        Data the image lacked ('normal', 'height', 'colour'); descriptors needing them are NaN.
    """

    values: dict
    patch_names: list
    patch_values: np.ndarray
    patch_centers_mm: np.ndarray
    patch_normals: np.ndarray
    patch_arc_mm: np.ndarray
    patch_kind: np.ndarray
    contour_mm: np.ndarray
    contour_normals: np.ndarray
    dpi: float
    patch_coverage: np.ndarray = None
    patch_contour_mm: np.ndarray = None
    face: str = "front"
    fragment: str = ""
    work_pixel_mm: float = WORK_PIXEL_MM
    missing_data: list = field(default_factory=list)
    boundary_names: list = field(default_factory=list)
    boundary_profile: np.ndarray = None
    boundary_step_mm: float = float("nan")

    def __post_init__(self):
        n = len(self.patch_arc_mm)
        if self.boundary_profile is None:
            self.boundary_profile = np.zeros((0, len(self.boundary_names)), np.float32)
        if self.patch_coverage is None:
            self.patch_coverage = np.ones(n)
        if self.patch_contour_mm is None:
            self.patch_contour_mm = np.full((n, 2), np.nan)

    @property
    def n_patches(self) -> int:
        return len(self.patch_arc_mm)

    def patch_column(self, name: str) -> np.ndarray:
        """Values of one patch descriptor, (N,)."""
        try:
            return self.patch_values[:, self.patch_names.index(name)]
        except ValueError:
            raise KeyError(f"no patch descriptor {name!r}; known: {self.patch_names}") from None

    def patch_indices(self, kind: str) -> np.ndarray:
        """Row indices of the patches of one kind ('p10' or 'p20')."""
        return np.flatnonzero(self.patch_kind == kind)


def _area_downsample(a, factor: int, shape) -> np.ndarray:
    """Block mean by an integer factor onto ``shape`` (the image is zero-padded to fit);
    (H, W) or (H, W, C) with C <= 4."""
    a = np.asarray(a, dtype=np.float32)
    if factor == 1:
        return a
    h, w = shape
    if a.shape[:2] != (h * factor, w * factor):
        pad = np.zeros((h * factor, w * factor) + a.shape[2:], np.float32)
        hh, ww = min(a.shape[0], h * factor), min(a.shape[1], w * factor)
        pad[:hh, :ww] = a[:hh, :ww]
        a = pad
    return cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)


def extract_features(image: RGBNImage, *, face: str = "front", fragment: str = "",
                     work_pixel_mm: float = WORK_PIXEL_MM,
                     contour_start_mm=None,
                     progress: Callable[[float, str], None] | None = None) -> FeatureTable:
    """All per-fragment and per-patch descriptors of one fragment face (§5.2.1, §5.4).

    Parameters
    ----------
    image : RGBNImage
        The face; ``normals`` None (colour-only) or ``height_mm`` None give NaN for the
        descriptors that need them, recorded in ``missing_data``. Non-finite albedo pixels
        count as black and non-finite normals as (0, 0, 1); non-finite heights are skipped.
    face, fragment : str
        Face name and fragment id stored with the table.
    work_pixel_mm : float
        Target pixel size of the working grid, mm.
    contour_start_mm : (2,) float, optional
        Start the contour (and the patch sampling) at the contour point nearest to this point
        (x, y mm); by default the point farthest from the centroid.
    progress : callable(fraction, text), optional
        Called as the work advances.

    Returns
    -------
    FeatureTable

    References
    ----------
    Toler-Franklin 2011, §5.2.1 (patches), §5.4 (descriptors, eqs. 5.1–5.4).

    Examples
    --------
    >>> yy, xx = np.mgrid[:240, :240]
    >>> mask = (yy - 120) ** 2 + (xx - 120) ** 2 < 100 ** 2
    >>> img = RGBNImage(np.full((240, 240, 3), 0.5), mask, dpi=100)
    >>> t = extract_features(img)
    >>> t.values["colour_variance"], bool(np.isnan(t.values["normal_z_mean"])), t.missing_data
    (0.0, True, ['height', 'normal'])
    """
    if not isinstance(image, RGBNImage):
        raise ValueError(f"image must be an RGBNImage, got {type(image).__name__}")
    if not work_pixel_mm > 0:
        raise ValueError(f"work_pixel_mm must be positive, got {work_pixel_mm}")
    if not image.mask.any():
        raise ValueError("image mask is empty: no fragment to describe")
    report = progress or (lambda f, t: None)
    px = image.pixel_mm
    factor = max(1, int(round(work_pixel_mm / px)))
    wp = px * factor
    H, W = image.shape
    shape = (-(-H // factor), -(-W // factor))
    has_n, has_h = image.normals is not None, image.height_mm is not None
    missing = sorted(({"normal"} if not has_n else set()) | ({"height"} if not has_h else set()))

    # --- the working grid: mask coverage and fragment-only block means -------------------------
    report(0.0, "working grid")
    m = image.mask.astype(np.float32)
    M = _area_downsample(m, factor, shape)
    safe = np.maximum(M, 1e-6)[..., None]
    m3 = cv2.merge([m, m, m])
    albedo = _area_downsample(cv2.multiply(image.albedo, m3), factor, shape) / safe
    if not np.isfinite(albedo).all():  # NaN pixels (e.g. saturated) count as black, not as NaN
        albedo = _area_downsample(cv2.multiply(np.nan_to_num(image.albedo, nan=0.0, posinf=1.0, neginf=0.0), m3),
                                  factor, shape) / safe
    # moment channels on the working grid, weighted by coverage M: every patch statistic is a
    # weighted sum over the patch disc (one einsum), equal to the statistic of the grid pixels
    # channels centred on the fragment means so float32 sums of squares do not cancel
    wsum = float(M.sum(dtype=np.float64))
    wmean = lambda a: float(np.tensordot(M, a, axes=2) / wsum)  # noqa: E731
    c_rgb = tuple(wmean(albedo[..., k]) for k in range(3))
    chans = colour_channels(albedo, c_rgb)
    c_n = None
    if has_n:
        normals = _area_downsample(cv2.multiply(image.normals, m3), factor, shape) / safe
        if not np.isfinite(normals).all():
            # unsolved pixels (NaN normals) read as facing the viewer rather than poisoning
            # every statistic of their grid cell and patch
            bad = ~np.isfinite(image.normals).all(axis=-1)
            fixed = np.where(bad[..., None], np.float32((0.0, 0.0, 1.0)), image.normals)
            normals = _area_downsample(cv2.multiply(fixed, m3), factor, shape) / safe
        c_n = {"L": float(np.dot(c_rgb, (0.2126, 0.7152, 0.0722)))}
        c_n.update({k: wmean(normals[..., i]) for i, k in enumerate(("nx", "ny", "nz"))})
        chans.update(normal_channels(albedo, normals, c_n))
    if has_h:
        ok = np.isfinite(image.height_mm) & image.mask
        # per fragment area, like the other channels: thickness = sum(w M h) / sum(w M hv)
        chans["h"] = _area_downsample(np.where(ok, image.height_mm, 0.0), factor, shape) / safe[..., 0]
        chans["hv"] = _area_downsample(ok.astype(np.float32), factor, shape) / safe[..., 0]
    keys = list(chans)
    kidx = {k: i for i, k in enumerate(keys)}
    stack = np.stack([chans[k] for k in keys])  # (C, H, W)

    def means(wts, sel=(slice(None), slice(None))):
        """Coverage-weighted means of every channel under the weights ``wts`` at ``sel``."""
        wm = wts * M[sel]
        tot = float(wm.sum(dtype=np.float64))
        if tot <= 0:
            return None
        sums = np.einsum("ij,kij->k", wm, stack[(slice(None),) + tuple(sel)]) / tot
        return {k: float(sums[i]) for k, i in kidx.items()}

    nan = float("nan")
    values = {d.name: nan for d in fragment_descriptors()}
    one = np.ones_like(M)
    mu = means(one)
    values.update(colour_from_moments(mu, c_rgb))
    region = M > 0.5
    inside = M > 0.99  # fully on the fragment: no edge pixels in the pixel statistics
    if has_n:
        values.update(normal_from_moments(mu, c_n))
        nz = np.where(M > 0, chans["nz"], 1.0).astype(np.float32)
        grey = np.where(M > 0, chans["L"], 0.0).astype(np.float32)
        # smoothed nz (background filled with the mean so the outline stays quiet) for the FFTs
        # and the discontinuity histogram: statistics of the surface, not of sensor noise or
        # of how the scan was resampled
        nz_s = ndi.gaussian_filter(np.where(region, nz, values["normal_z_mean"]).astype(np.float32), 1.0)
        values.update(discontinuity_from_differences(neighbour_differences(nz_s, inside)))
        report(0.2, "fragment orientation")
        if region.any():
            values.update(_fragment_orientation(nz_s, region, wp))
        report(0.3, "erosion")
        ms, eroded = _multiscale_erosion(grey, nz, M, wp, n_scales=EROSION_SCALES)
        values.update(ms)
    if has_h:
        if mu["hv"] > 0:
            values["thickness_mean"] = mu["h"] / mu["hv"]

    # --- contour and patches -------------------------------------------------------------------
    report(0.45, "contour and patches")
    names = [d.name for d in patch_descriptors()]
    col = {n: i for i, n in enumerate(names)}
    try:
        contour = fragment_contour(M, wp, start_mm=contour_start_mm)
    except ValueError:
        contour = None
    if contour is None or contour.length_mm < PATCH_SPACING_MM:
        patches = None
    else:
        patches = sample_patches(contour, M, wp)
    n_p = len(patches) if patches is not None else 0
    pv = np.full((n_p, len(names)), np.nan)
    if n_p:
        # curvature belongs to the contour point, shared by the patch kinds at one arc position
        arcs, inv = np.unique(patches.arc_mm, return_inverse=True)
        cpts, _ = contour.at(arcs)
        for s in CURVATURE_SCALES_MM:
            pv[:, col[f"curv_area_{s:g}"]] = area_curvature(M, wp, cpts, s)[inv]
            if 2 * s < contour.length_mm:  # else the three points would wrap around the fragment
                pv[:, col[f"curv_3pt_{s:g}"]] = three_point_curvature(contour, arcs, s)[inv]
    for i in range(n_p):
        if i % 16 == 0:
            report(0.5 + 0.5 * i / n_p, f"patch {i + 1}/{n_p}")
        if patches.coverage[i] < MIN_COVERAGE:
            continue
        rows, cols, w, _ = disk_window(patches.centers_mm[i], patches.diameter_mm[i] / 2, wp, M.shape)
        sel = (rows, cols)
        pm = means(w, sel)
        row = colour_from_moments(pm, c_rgb)
        in_disc = (w > 0.5) & region[sel]
        if has_n:
            row.update(normal_from_moments(pm, c_n))
            row.update(discontinuity_from_differences(neighbour_differences(nz_s[sel], inside[sel] & (w > 0.5))))
            row.update(_patch_orientation(nz_s[sel], in_disc, wp, patches.normals[i]))
            d, s = erosion_statistics(eroded[sel], in_disc, wp)
            row["erosion_density"], row["erosion_size"] = d, s
        if has_h:
            row["thickness_mean"] = pm["h"] / pm["hv"] if pm["hv"] > 0 else nan
        for k, v in row.items():
            if k in col:
                pv[i, col[k]] = v
    boundary, step = np.zeros((0, 0), np.float32), float("nan")
    if contour is not None:
        thick = np.where(chans["hv"] > 0, chans["h"] / np.maximum(chans["hv"], 1e-6), np.nan) if has_h else None
        boundary, step = boundary_profile(contour, albedo, wp, weight=M, thickness_mm=thick)
    report(1.0, "done")
    empty2 = np.zeros((0, 2))
    return FeatureTable(
        values=values, patch_names=names, patch_values=pv,
        patch_centers_mm=patches.centers_mm if n_p else empty2,
        patch_normals=patches.normals if n_p else empty2,
        patch_arc_mm=patches.arc_mm if n_p else np.zeros(0),
        patch_kind=patches.kind if n_p else np.zeros(0, dtype="U8"),
        patch_coverage=patches.coverage if n_p else np.zeros(0),
        patch_contour_mm=patches.contour_mm if n_p else empty2,
        contour_mm=contour.points_mm if contour is not None else empty2,
        contour_normals=contour.normals if contour is not None else empty2,
        dpi=image.dpi, face=face, fragment=fragment, work_pixel_mm=wp, missing_data=missing,
        boundary_names=boundary_channel_names() if len(boundary) else [], boundary_profile=boundary,
        boundary_step_mm=step)


def _patch_orientation(z, region, wp, normal) -> dict:
    """Dominant orientation of one patch window, on at most _PATCH_FFT_PX pixels per side (a
    20 mm patch on the 0.085 mm grid is halved: its Nyquist stays at 3 cycles/mm)."""
    f = int(np.ceil(max(z.shape) / _PATCH_FFT_PX))
    if f > 1:
        h, w = z.shape[0] // f, z.shape[1] // f
        z = z[:h * f, :w * f].reshape(h, f, w, f).mean(axis=(1, 3))
        region = region[:h * f, :w * f].reshape(h, f, w, f).mean(axis=(1, 3)) > 0.5
        wp = wp * f
    return dominant_orientation(z, region, wp, smooth_px=0, reference_normal=normal)


def _fragment_orientation(nz_s, region, wp) -> dict:
    """Dominant frequency and amplitude of the whole fragment (its angle has no reference)."""
    rr, cc = np.nonzero(region)
    sel = (slice(rr.min(), rr.max() + 1), slice(cc.min(), cc.max() + 1))
    z, r = nz_s[sel], region[sel].astype(np.float32)
    f = max(1.0, max(z.shape) / _FFT_MAX_PX)
    p = wp
    if f > 1:
        size = (max(4, int(z.shape[1] / f)), max(4, int(z.shape[0] / f)))
        z = cv2.resize(z, size, interpolation=cv2.INTER_AREA)
        r = cv2.resize(r, size, interpolation=cv2.INTER_AREA)
        p = wp * nz_s[sel].shape[1] / size[0]
    d = dominant_orientation(z, r > 0.5, p, smooth_px=0)
    return {"orient_frequency": d["orient_frequency"], "orient_amplitude": d["orient_amplitude"]}


# --- storage -----------------------------------------------------------------------------------

def write_features(group: h5py.Group, table: FeatureTable) -> None:
    """Write one feature table into an open HDF5 group."""
    group.attrs["dpi"] = table.dpi
    group.attrs["face"] = table.face
    group.attrs["fragment"] = table.fragment
    group.attrs["work_pixel_mm"] = table.work_pixel_mm
    group.attrs["missing_data"] = json.dumps(list(table.missing_data))
    group.attrs["frame"] = "fragment frame, mm: x = col * pixel_mm (right), y = row * pixel_mm (down)"
    str_t = h5py.string_dtype()
    names = list(table.values)
    group.create_dataset("fragment_names", data=np.array(names, dtype=object), dtype=str_t)
    group.create_dataset("fragment_values", data=np.array([table.values[n] for n in names], float))
    group.create_dataset("patch_names", data=np.array(list(table.patch_names), dtype=object), dtype=str_t)
    group.create_dataset("patch_values", data=np.asarray(table.patch_values, float).reshape(-1, len(table.patch_names)))
    group.create_dataset("patch_kind", data=np.asarray(table.patch_kind, dtype=object), dtype=str_t)
    for name in ("patch_centers_mm", "patch_normals", "patch_contour_mm", "contour_mm", "contour_normals"):
        group.create_dataset(name, data=np.asarray(getattr(table, name), float).reshape(-1, 2))
    for name in ("patch_arc_mm", "patch_coverage"):
        group.create_dataset(name, data=np.asarray(getattr(table, name), float).reshape(-1))
    group.attrs["boundary_step_mm"] = float(table.boundary_step_mm)
    group.create_dataset("boundary_names", data=np.array(list(table.boundary_names), dtype=object), dtype=str_t)
    group.create_dataset("boundary_profile", data=np.asarray(table.boundary_profile, np.float32)
                         .reshape(-1, len(table.boundary_names)))


def read_features(group: h5py.Group) -> FeatureTable:
    """Read a table written by :func:`write_features`."""
    try:
        dec = lambda ds: [x.decode() if isinstance(x, bytes) else str(x) for x in ds[()]]  # noqa: E731
        names = dec(group["fragment_names"])
        vals = group["fragment_values"][()]
        return FeatureTable(
            values={n: float(v) for n, v in zip(names, vals)},
            patch_names=dec(group["patch_names"]),
            patch_values=group["patch_values"][()],
            patch_centers_mm=group["patch_centers_mm"][()],
            patch_normals=group["patch_normals"][()],
            patch_arc_mm=group["patch_arc_mm"][()],
            patch_kind=np.array(dec(group["patch_kind"]), dtype="U8"),
            patch_coverage=group["patch_coverage"][()],
            patch_contour_mm=group["patch_contour_mm"][()],
            contour_mm=group["contour_mm"][()],
            contour_normals=group["contour_normals"][()],
            dpi=float(group.attrs["dpi"]),
            face=str(group.attrs["face"]),
            fragment=str(group.attrs.get("fragment", "")),
            work_pixel_mm=float(group.attrs["work_pixel_mm"]),
            missing_data=json.loads(group.attrs.get("missing_data", "[]")),
            # schema 1 tables have no boundary profile: the matcher falls back to the patch ranking
            boundary_names=dec(group["boundary_names"]) if "boundary_names" in group else [],
            boundary_profile=group["boundary_profile"][()] if "boundary_profile" in group else None,
            boundary_step_mm=float(group.attrs.get("boundary_step_mm", np.nan)))
    except KeyError as exc:
        raise ArtifactError(f"feature table in {group.file.filename} lacks {exc}") from exc


def save_features(store: Store, relpath: str, tables: FeatureTable | Mapping[str, FeatureTable], *,
                  provenance: Mapping | None = None) -> ArtifactRef:
    """Store one table, or ``{face: table}``, as an immutable ``tessera.features`` artifact.

    Each table goes to the group named by its face (``/front``, ``/back``).
    """
    if isinstance(tables, FeatureTable):
        tables = {tables.face: tables}
    if not tables:
        raise ValueError("tables must hold at least one FeatureTable")

    def fill(f):
        f.attrs["faces"] = json.dumps(sorted(tables))
        for face, t in tables.items():
            write_features(f.create_group(face), t)

    return store.write(relpath, SCHEMA, SCHEMA_VERSION, fill, provenance=provenance)


def load_features(store: Store, ref: ArtifactRef | Mapping | str, face: str | None = None) -> FeatureTable:
    """Load (and digest-check, when given a pointer) the table of ``face`` (default: the only or
    the front one) from a ``tessera.features`` artifact."""
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        faces = [k for k in f.keys() if isinstance(f[k], h5py.Group)]
        if face is None:
            face = "front" if "front" in faces else (faces[0] if len(faces) == 1 else None)
        if face is None or face not in faces:
            raise ArtifactError(f"feature artifact {f.filename} has faces {faces}; asked for {face!r}")
        return read_features(f[face])
