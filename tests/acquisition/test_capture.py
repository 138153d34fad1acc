"""Tests of the capture workflow and the scans artifact (common/acquisition/capture.py)."""

import numpy as np
import pytest

from common.acquisition.capture import (CaptureStep, NoFragmentError, ScannerError, capture_fragment, read_scans,
                                        simulated_operator, write_scans)
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface
from common.store import ArtifactError, Store


@pytest.fixture
def sim():
    s = SimulatedFlatbed(bed_mm=(100, 100), seed=7)
    s.place(demo_surface(20, 100, seed=2), centre_mm=(50, 50))
    return s


def test_full_capture_is_four_rotations_per_face_with_operator_steps(sim):
    steps = []
    act = simulated_operator(sim)

    def operator(step: CaptureStep):
        steps.append(step)
        act(step)

    res = capture_fragment(sim, "F0001", operator=operator, dpi=100, prescan_dpi=25, depth=16)
    assert [s.action for s in steps] == ["place", "rotate", "rotate", "rotate", "flip", "rotate", "rotate", "rotate"]
    assert [s.index for s in steps] == list(range(1, 9)) and all(s.total == 8 for s in steps)
    assert steps[0].instruction.startswith("Place the fragment face down")
    assert "90° clockwise" in steps[1].instruction and "Flip" in steps[4].instruction
    assert [sc.rotation for sc in res.scans["front"]] == [0, 90, 180, 270]
    assert len(res.scans["back"]) == 4
    # each full-dpi scan covers the fragment where it lay at that moment (+ margin)
    for rec in [r for r in sim.history if r.dpi == 100]:
        x0, y0, x1, y1 = rec.area_mm
        assert x0 < 50 + 12 and x1 > 50 - 12 and x1 - x0 < 40
    assert res.scans["front"][0].image.dtype == np.uint16


def test_colour_only_takes_one_scan_per_face(sim):
    res = capture_fragment(sim, "F0002", operator=simulated_operator(sim), dpi=100, prescan_dpi=25,
                           colour_only=True, depth=8)
    assert len(res.scans["front"]) == 1 and len(res.scans["back"]) == 1
    assert res.colour_only and res.scans["front"][0].image.dtype == np.uint8


def test_empty_bed_raises_no_fragment_with_operator_message():
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=7)
    with pytest.raises(NoFragmentError) as err:
        capture_fragment(sim, "F0003", operator=lambda step: None, dpi=100, prescan_dpi=25)
    assert "Place the fragment" in err.value.operator_message


def test_bad_arguments_are_named():
    sim = SimulatedFlatbed(bed_mm=(100, 100))
    with pytest.raises(ValueError, match="depth"):
        capture_fragment(sim, "F", operator=lambda s: None, depth=12)
    with pytest.raises(ValueError, match="fragment_id"):
        capture_fragment(sim, "", operator=lambda s: None)


def test_scans_artifact_round_trip_and_digest_check(sim, tmp_path):
    res = capture_fragment(sim, "F0004", operator=simulated_operator(sim), dpi=100, prescan_dpi=25,
                           colour_only=True, calibration="calibration/sim/x.h5")
    store = Store(tmp_path)
    ref = write_scans(store, "F0004", res)
    assert ref.path.startswith("fragments/F0004/scans/")
    assert write_scans(store, "F0004", res) == ref            # same pixels, same artifact
    back = read_scans(store, ref)
    assert back.device == "sim" and back.calibration == "calibration/sim/x.h5" and back.colour_only
    np.testing.assert_array_equal(back.scans["front"][0].image, res.scans["front"][0].image)
    assert back.scans["back"][0].area_mm == pytest.approx(res.scans["back"][0].area_mm)
    with open(store.path(ref.path), "r+b") as fh:            # corrupt one byte
        fh.seek(ref.bytes // 2)
        b = fh.read(1)
        fh.seek(ref.bytes // 2)
        fh.write(bytes([b[0] ^ 0xFF]))
    with pytest.raises(ArtifactError):
        read_scans(store, ref)


def test_check_scan_converts_grey_float_and_rgba_and_refuses_the_rest():
    from common.acquisition.capture import check_scan
    rng = np.random.default_rng(0)
    grey = rng.integers(1000, 60000, (20, 30)).astype(np.uint16)
    out = check_scan(grey, "g")
    assert out.shape == (20, 30, 3) and out.dtype == np.uint16 and (out[..., 1] == grey).all()
    f = rng.uniform(0.1, 0.9, (20, 30, 3)).astype(np.float32)
    assert np.allclose(check_scan(f).astype(np.float64) / 65535, f, atol=1e-5)
    rgba = np.dstack([grey, grey, grey, np.full_like(grey, 65535)])
    assert check_scan(rgba).shape == (20, 30, 3)
    for bad, reason in [((grey // 300).astype(np.uint16), "front scan 1: a 16-bit scan holding 8-bit values"),
                        (np.zeros((20, 30, 3), np.uint8), "front scan 1: all black"),
                        (np.full((20, 30, 3), 128, np.uint8), "front scan 1: blank"),
                        (f * 3, "front scan 1: float samples span"),
                        (grey.astype(np.int32), "front scan 1: samples of type int32"),
                        (np.zeros((20, 30, 5), np.uint8), "front scan 1: shape")]:
        with pytest.raises(ValueError, match=reason):
            check_scan(bad, "front scan 1")
    with pytest.raises(ValueError, match="8-bit samples but 16-bit was declared"):
        check_scan(f.astype(np.uint8) + 1, "x", depth=16)


def test_a_scanner_in_grey_mode_is_handled_and_one_giving_black_frames_is_named(sim):
    class Grey:
        def __init__(self, inner, black=False):
            self.inner, self.black, self.name, self.bed_mm = inner, black, "grey", inner.bed_mm

        def scan(self, area, dpi, depth):
            img = self.inner.scan(area, dpi, depth)
            if self.black and area is not None:
                return np.zeros_like(img)
            return img.mean(axis=2).astype(img.dtype)
    res = capture_fragment(Grey(sim), "F9", operator=simulated_operator(sim), dpi=100, prescan_dpi=25,
                           colour_only=True)
    assert res.scans["front"][0].image.ndim == 3 and res.scans["front"][0].image.shape[2] == 3
    with pytest.raises(ScannerError, match="front scan 0: all black"):
        capture_fragment(Grey(sim, black=True), "F9", operator=simulated_operator(sim), dpi=100, prescan_dpi=25,
                         colour_only=True)


def test_a_real_scanners_operator_is_prompted_where_the_station_speaks_and_a_closed_input_is_named(monkeypatch):
    """On a real flatbed the operator's prompts go to the station's output (not always stdout, as input()
    writes them), and a terminal whose input is closed ends the wait with EOFError instead of hanging."""
    import io
    from types import SimpleNamespace

    from services.scanner import ask, terminal_operator

    out = io.StringIO()
    monkeypatch.setattr("sys.stdin", io.StringIO("\nRPf_7\n"))
    operator = terminal_operator(scanner=None, simulated=False, out=out)
    operator(SimpleNamespace(index=1, total=4, instruction="turn the fragment by 90 degrees"))
    assert ask("fragment id: ", out) == "RPf_7"
    shown = out.getvalue()
    assert "[1/4] turn the fragment by 90 degrees" in shown
    assert "press Enter when done" in shown and shown.rstrip().endswith("fragment id:")
    with pytest.raises(EOFError, match="input is closed"):
        ask("fragment id: ", out)
