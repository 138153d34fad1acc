"""The descriptor registry and correspondence rules (common/features/registry.py)."""

import numpy as np
import pytest

from common.features.registry import (CURVATURE_SCALES_MM, DESCRIPTORS, Descriptor, correspondence,
                                      fragment_descriptors, patch_descriptors)


def test_every_descriptor_of_section_5_4_is_registered():
    frag = {d.name for d in fragment_descriptors()}
    patch = {d.name for d in patch_descriptors()}
    common = {"colour_mean_r", "colour_mean_g", "colour_mean_b", "colour_variance", "saturation",
              "normal_z_mean", "normal_z_variance", "colour_normal_svd", "disc_ratio_80_50",
              "disc_frac_046", "disc_skewness", "disc_kurtosis", "orient_frequency", "orient_amplitude",
              "thickness_mean"}
    assert common <= frag and common <= patch
    assert {"orient_angle", "erosion_density", "erosion_size"} <= patch
    assert {f"erosion_density_s{k}" for k in range(10)} <= frag
    for s in CURVATURE_SCALES_MM:
        assert {f"curv_area_{s:g}", f"curv_3pt_{s:g}"} <= patch


def test_names_are_unique_per_level_and_keys_carry_the_level():
    for level in ("fragment", "patch"):
        names = [d.name for d in DESCRIPTORS.values() if d.level == level]
        assert len(names) == len(set(names))
    assert all(k == f"{d.level}.{d.name}" for k, d in DESCRIPTORS.items())


def test_every_descriptor_states_a_finite_tolerance_and_a_unit():
    for d in DESCRIPTORS.values():
        assert np.isfinite(d.tolerance) and d.tolerance > 0, d.key
        assert d.unit and d.doc, d.key


def test_signed_curvature_uses_abs_sum_and_angles_wrap():
    assert all(d.rule == "abs_sum" for d in DESCRIPTORS.values() if d.group == "curvature")
    assert DESCRIPTORS["patch.orient_angle"].rule == "angle_diff"


@pytest.mark.parametrize("a,b,rule,expect", [
    (0.3, 0.1, "abs_diff", 0.2),
    (0.1, -0.1, "abs_sum", 0.0),      # convex meets equally concave: perfect
    (0.1, 0.1, "abs_sum", 0.2),
    (175.0, 5.0, "angle_diff", 10.0),  # axial angles wrap at 180
    (90.0, 0.0, "angle_diff", 90.0),
    (10.0, 370.0, "angle_diff", 0.0),
])
def test_correspondence_rules(a, b, rule, expect):
    d = Descriptor("x", "patch", frozenset(), rule, "normal", "1", "test", period=180.0, tolerance=1.0)
    assert correspondence(d, a, b) == pytest.approx(expect)


def test_correspondence_is_vectorised_and_propagates_missing_values():
    d = DESCRIPTORS["patch.colour_mean_r"]
    out = correspondence(d, np.array([0.1, np.nan]), np.array([0.4, 0.2]))
    assert out[0] == pytest.approx(0.3) and np.isnan(out[1])


def test_bad_descriptor_declaration_is_refused():
    with pytest.raises(ValueError, match="rule"):
        Descriptor("x", "patch", frozenset(), "cosine", "normal", "1", "")
    with pytest.raises(ValueError, match="needs"):
        Descriptor("x", "patch", frozenset({"depth"}), "abs_diff", "normal", "1", "")
    with pytest.raises(ValueError, match="period"):
        Descriptor("x", "patch", frozenset(), "angle_diff", "normal", "deg", "")


def _tolerance_text(d: Descriptor) -> str:
    text = f"{d.tolerance:g}"
    return text + (f" + {d.rel_tolerance:g}·max(\\|a\\|,\\|b\\|)" if d.rel_tolerance else "")


def test_the_descriptor_table_of_docs_features_md_is_the_registry():
    """Every row of the docs' table states the registry's needs, rule, unit and tolerance (the
    tolerances had drifted from the ones the invariance tests use)."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "features.md").read_text()
    rows = [line for line in text.splitlines() if re.match(r"\| (fragment|patch) \| `", line)]
    seen = set()
    for line in rows:
        level, name, needs, rule, unit, tolerance, _ = [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        name = name.strip("`")
        names = [f"{name.split('_s0')[0]}_s{k}" for k in range(10)] if "…" in name else [name]
        for n in names:
            d = DESCRIPTORS[f"{level}.{n}"]
            seen.add(d.key)
            assert needs == (", ".join(x for x in ("colour", "normal", "height") if x in d.needs) or "–"), d.key
            assert (rule, unit) == (d.rule, d.unit), d.key
            assert _tolerance_text(d) in tolerance, (d.key, tolerance)
    assert seen == set(DESCRIPTORS)
