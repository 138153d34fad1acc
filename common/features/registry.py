"""The descriptor registry: every feature the extractor computes, declared once (§5.2.1, §5.4).

Each :class:`Descriptor` says at which level it is computed (``'fragment'``: one value per
fragment face; ``'patch'``: one value per contour patch), which data it needs (``'colour'``,
``'normal'``, ``'height'``; when an RGBN image lacks them the value is NaN), how two values are
compared (the *correspondence* of §5.2.2: ``abs_diff`` = |a − b|, ``abs_sum`` = |a + b| for
signed contour curvature, because a convex stretch of one fragment meets a concave stretch of
its neighbour, ``angle_diff`` = the wrapped difference of axial angles), its group, unit and the
rotation/noise tolerance that the invariance tests hold it to.

The matcher iterates :data:`DESCRIPTORS` (or :func:`fragment_descriptors` /
:func:`patch_descriptors`, which give the column order of a :class:`~common.features.table.FeatureTable`)
and looks values up by ``descriptor.name``: ``table.values[name]`` at fragment level,
``table.patch_column(name)`` at patch level. Keys of :data:`DESCRIPTORS` are
``"<level>.<name>"`` because most descriptors exist at both levels under the same name.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: contour-curvature scales of §5.4 (disc radius for eq. 5.1, arc half-span for eq. 5.2), mm
CURVATURE_SCALES_MM = (2.5, 5.0, 8.0, 10.0, 15.0)
#: number of structuring-element sizes of the per-fragment (multi-scale) erosion descriptor
EROSION_SCALES = 10

LEVELS = ("fragment", "patch")
NEEDS = ("colour", "normal", "height")
RULES = ("abs_diff", "abs_sum", "angle_diff")
GROUPS = ("colour", "curvature", "normal", "erosion", "thickness")


@dataclass(frozen=True)
class Descriptor:
    """One feature.

    Attributes
    ----------
    name : str
        Column name in the feature table (unique within its level).
    level : {'fragment', 'patch'}
    needs : frozenset of {'colour', 'normal', 'height'}
        Data the descriptor is computed from; missing data gives NaN.
    rule : {'abs_diff', 'abs_sum', 'angle_diff'}
        Correspondence of two values (§5.2.2).
    group : {'colour', 'curvature', 'normal', 'erosion', 'thickness'}
    unit : str
        Physical unit ('1' for dimensionless).
    doc : str
        One line: what it measures and where the thesis defines it.
    period : float
        Period of an angle (``angle_diff`` only), in ``unit``.
    tolerance : float
        Largest change the invariance tests accept when the fragment is rotated by an arbitrary
        angle or scanner noise is added (absolute, in ``unit``), plus ``rel_tolerance`` times the
        larger magnitude of the two values: the measured worst case x ~1.3-1.5 over generated
        60 mm fragments at 150 dpi (seeds 0-4; ``tests/features/test_table.py`` runs 0 and 1).
        The dominant-orientation ones hold on a fragment with a clear stroke pattern: where no
        orientation dominates, the strongest peak may jump between near-equal ones.
    rel_tolerance : float
        Relative part of the tolerance.
    """

    name: str
    level: str
    needs: frozenset
    rule: str
    group: str
    unit: str
    doc: str
    period: float = 0.0
    tolerance: float = np.inf
    rel_tolerance: float = 0.0

    def __post_init__(self):
        if self.level not in LEVELS:
            raise ValueError(f"level must be one of {LEVELS}, got {self.level!r}")
        if not set(self.needs) <= set(NEEDS):
            raise ValueError(f"needs must be a subset of {NEEDS}, got {sorted(self.needs)}")
        if self.rule not in RULES:
            raise ValueError(f"rule must be one of {RULES}, got {self.rule!r}")
        if self.group not in GROUPS:
            raise ValueError(f"group must be one of {GROUPS}, got {self.group!r}")
        if self.rule == "angle_diff" and not self.period > 0:
            raise ValueError(f"descriptor {self.name}: angle_diff needs a positive period")

    @property
    def key(self) -> str:
        return f"{self.level}.{self.name}"


def correspondence(descriptor: Descriptor, a, b):
    """Correspondence of two descriptor values (§5.2.2): small means the two agree.

    Parameters
    ----------
    descriptor : Descriptor
    a, b : float or array_like
        Values of the same descriptor on two fragments (or two patches); NaN propagates.

    Returns
    -------
    float or ndarray
        ``|a - b|`` (``abs_diff``), ``|a + b|`` (``abs_sum``, signed curvature: a convex edge meets
        a concave one) or the wrapped difference ``min(d, period - d)`` with
        ``d = |a - b| mod period`` (``angle_diff``).

    Examples
    --------
    >>> correspondence(DESCRIPTORS["patch.orient_angle"], 175.0, 5.0)
    10.0
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if descriptor.rule == "abs_diff":
        out = np.abs(a - b)
    elif descriptor.rule == "abs_sum":
        out = np.abs(a + b)
    else:
        d = np.mod(np.abs(a - b), descriptor.period)
        out = np.minimum(d, descriptor.period - d)
    return out.item() if out.ndim == 0 else out


def _build() -> dict[str, Descriptor]:
    C, N, H = frozenset({"colour"}), frozenset({"normal"}), frozenset({"height"})
    CN = frozenset({"colour", "normal"})
    both = ("fragment", "patch")
    rows = []

    def add(name, levels, needs, rule, group, unit, doc, tol, period=0.0, rel=0.0):
        # tol: one absolute tolerance, or {level: tolerance}; measured worst case x ~1.5
        for level in levels:
            t = tol[level] if isinstance(tol, dict) else tol
            rows.append(Descriptor(name, level, needs, rule, group, unit, doc, period, t, rel))

    for ch in "rgb":
        add(f"colour_mean_{ch}", both, C, "abs_diff", "colour", "1",
            f"mean linear albedo of the {ch.upper()} channel (§5.4.1)", {"fragment": 0.005, "patch": 0.01})
    add("colour_variance", both, C, "abs_diff", "colour", "1",
        "colour variance: sum of the R, G, B variances (§5.4.1)", {"fragment": 0.001, "patch": 0.003})
    add("saturation", both, C, "abs_diff", "colour", "1",
        "mean HSV saturation (max - min) / max (§5.4.1)", {"fragment": 0.005, "patch": 0.01})
    add("normal_z_mean", both, N, "abs_diff", "normal", "1",
        "mean z component of the unit normal (§5.4.3)", {"fragment": 0.002, "patch": 0.008})
    add("normal_z_variance", both, N, "abs_diff", "normal", "1",
        "variance of the normal z component (§5.4.3)", {"fragment": 0.0006, "patch": 0.003})
    add("colour_normal_svd", both, CN, "abs_diff", "normal", "1",
        "colour/normal variation: sum of singular values of the centred n x 4 stack "
        "(luminance, nx, ny, nz) / sqrt(n), eq. 5.3", {"fragment": 0.03, "patch": 0.06})
    add("disc_ratio_80_50", both, N, "abs_diff", "normal", "1",
        "normal discontinuity: 80th / 50th percentile of the neighbour |dnz| (§5.4.4)",
        {"fragment": 0.05, "patch": 0.15}, rel=0.2)
    add("disc_frac_046", both, N, "abs_diff", "normal", "1",
        "normal discontinuity: fraction of neighbour |dnz| above 0.46 (§5.4.4)", 0.01)
    add("disc_skewness", both, N, "abs_diff", "normal", "1",
        "normal discontinuity: third standardised moment of the neighbour |dnz| (§5.4.4)",
        {"fragment": 0.3, "patch": 2.0}, rel=0.6)
    add("disc_kurtosis", both, N, "abs_diff", "normal", "1",
        "normal discontinuity: fourth standardised moment of the neighbour |dnz| (§5.4.4)",
        {"fragment": 2.0, "patch": 10.0}, rel=1.0)
    add("orient_frequency", both, N, "abs_diff", "normal", "1/mm",
        "dominant orientation: frequency of the strongest FFT peak of smoothed nz above "
        "omega_min = 3 cycles per window (§5.4.5)", 0.08)
    add("orient_amplitude", both, N, "abs_diff", "normal", "1",
        "dominant orientation: amplitude of that peak, in nz units (§5.4.5)",
        {"fragment": 0.003, "patch": 0.0003})
    add("orient_angle", ("patch",), N, "angle_diff", "normal", "deg",
        "dominant orientation: angle of the peak's wave vector relative to the outward contour "
        "normal, axial in [0, 180), eq. 5.4", 6.0, period=180.0)
    add("erosion_density", ("patch",), CN, "abs_diff", "erosion", "1",
        "cracking/erosion: fraction of pixels in black top-hat(colour) and white top-hat(normals) "
        "above 0.3, disk radius 3 (§5.4.6)", 0.02)
    add("erosion_size", ("patch",), CN, "abs_diff", "erosion", "mm2",
        "cracking/erosion: area-weighted mean area of the eroded components in the patch (§5.4.6)",
        1.5)
    for k in range(EROSION_SCALES):
        add(f"erosion_density_s{k}", ("fragment",), CN, "abs_diff", "erosion", "1",
            f"multi-scale erosion density at structuring-element size {k} (§5.4.6)", 0.015)
        add(f"erosion_size_s{k}", ("fragment",), CN, "abs_diff", "erosion", "mm2",
            f"multi-scale area-weighted mean eroded-component area at size {k} (§5.4.6)", 2.0,
            rel=0.2 if k < 5 else 0.7)  # at coarse sizes neighbouring components merge or not
    add("thickness_mean", both, H, "abs_diff", "thickness", "mm",
        "mean of the height/thickness map where it exists (§5.4.7)", 0.03)
    area_tol = {2.5: 0.06, 5.0: 0.02, 8.0: 0.008, 10.0: 0.006, 15.0: 0.004}
    three_tol = {2.5: 0.03, 5.0: 0.008, 8.0: 0.004, 10.0: 0.003, 15.0: 0.003}
    for s in CURVATURE_SCALES_MM:
        add(f"curv_area_{s:g}", ("patch",), frozenset(), "abs_sum", "curvature", "1/mm",
            f"signed contour curvature from the disc area at radius {s:g} mm, eq. 5.1 "
            "(convex > 0)", area_tol[s])
        add(f"curv_3pt_{s:g}", ("patch",), frozenset(), "abs_sum", "curvature", "1/mm",
            f"signed contour curvature of the circle through three contour points {s:g} mm "
            "apart, eq. 5.2 (convex > 0)", three_tol[s])
    return {d.key: d for d in rows}


#: every descriptor, keyed ``"<level>.<name>"``
DESCRIPTORS: dict[str, Descriptor] = _build()


def fragment_descriptors() -> list[Descriptor]:
    """Fragment-level descriptors, in the order of ``FeatureTable.values``."""
    return [d for d in DESCRIPTORS.values() if d.level == "fragment"]


def patch_descriptors() -> list[Descriptor]:
    """Patch-level descriptors, in the column order of ``FeatureTable.patch_values``."""
    return [d for d in DESCRIPTORS.values() if d.level == "patch"]
