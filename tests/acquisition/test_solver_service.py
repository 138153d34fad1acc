"""Tests of the solver service shell (services/solver.py) with a stand-in stage context."""

import logging

import numpy as np
import pytest

from common.acquisition.capture import capture_fragment, simulated_operator, write_scans
from common.acquisition.errors import CalibrationError
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface
from common.messages import MessageError, new_message, validate
from common.rgbn.image import load_rgbn
from common.store import Store
from services import solver


class Ctx:
    def __init__(self, store, config=None):
        self.store, self.config = store, config or {}
        self.log = logging.getLogger("test.solver")
        self.reports = []

    def progress(self, fraction, text):
        self.reports.append((fraction, text))


def _fragment_ready(store, colour_only=False, device="sim"):
    sim = SimulatedFlatbed(device, bed_mm=(100, 100), seed=8)
    sim.place(demo_surface(20, 150, seed=3), centre_mm=(50, 50))
    res = capture_fragment(sim, "F0100", operator=simulated_operator(sim), dpi=150, prescan_dpi=25,
                           colour_only=colour_only)
    ref = write_scans(store, "F0100", res)
    return new_message("fragment.ready", fragment="F0100", artifact=ref)


def test_fragment_ready_gives_one_rgbn_ready_per_face_and_is_idempotent(tmp_path):
    store = Store(tmp_path)
    job = _fragment_ready(store)
    ctx = Ctx(store)
    events = solver.handle(job, ctx)
    assert [e["face"] for e in events] == ["front", "back"]
    for e in events:
        validate(e)
        assert e["type"] == "rgbn.ready" and e["artifact"]["path"].startswith("fragments/F0100/rgbn/")
        img = load_rgbn(store, e["artifact"])
        assert img.has_normals and img.confidence is not None and img.mask.sum() > 1000
        inside = img.normals[img.mask]
        assert np.allclose(np.linalg.norm(inside, axis=1), 1, atol=1e-4) and (inside[:, 2] > 0.5).mean() > 0.95
    assert ctx.reports[-1][0] == 1.0
    again = solver.handle(job, Ctx(store))                 # re-delivered job: same artifacts
    assert [e["artifact"] for e in again] == [e["artifact"] for e in events]
    assert len(list((tmp_path / "calibration" / "sim").glob("*.h5"))) == 1   # calibrated once, on first use


def test_colour_only_capture_gives_albedo_without_normals(tmp_path):
    store = Store(tmp_path)
    events = solver.handle(_fragment_ready(store, colour_only=True), Ctx(store))
    img = load_rgbn(store, events[0]["artifact"])
    assert not img.has_normals and img.albedo[img.mask].mean() > 0.2


def test_real_device_without_calibration_fails_clearly(tmp_path):
    store = Store(tmp_path)
    job = _fragment_ready(store, device="epson2:libusb:001:004")
    with pytest.raises(CalibrationError, match="tessera calibrate") as err:
        solver.handle(job, Ctx(store))
    # a bare `tessera calibrate` would calibrate the station's [scanner] device, not this one: the
    # message names the commands for this device and how to re-queue the parked job
    msg = str(err.value)
    assert "tessera calibrate --nominal --lamp-direction-deg D --device epson2:libusb:001:004" in msg, msg
    assert "--from-files MANIFEST --device epson2:libusb:001:004" in msg, msg
    assert "tessera status --rerun" in msg, msg


def test_a_message_that_contradicts_its_scans_artifact_is_refused_naming_both(tmp_path):
    """The solver took the scanner (and colour-only) from the scans artifact and ignored the message's, so a
    message naming another device was solved with the artifact's device's calibration, silently. A message
    that repeats the artifact's values is solved; one that contradicts them is refused naming both, and
    nothing is written."""
    store = Store(tmp_path)
    job = _fragment_ready(store)
    for field, value in (("device", "epson-v850"), ("colour_only", True)):
        with pytest.raises(MessageError, match=f"{field} .*contradicts the scans artifact") as err:
            solver.handle(dict(job, **{field: value}), Ctx(store))
        assert repr(value) in str(err.value)
    assert not (tmp_path / "fragments" / "F0100" / "rgbn").exists()
    assert not (tmp_path / "calibration").exists()
    events = solver.handle(dict(job, device="sim", colour_only=False), Ctx(store))
    assert [e["face"] for e in events] == ["front", "back"]


def test_wrong_message_type_is_rejected(tmp_path):
    with pytest.raises(MessageError):
        solver.handle(new_message("rgbn.ready", fragment="F", face="front",
                                  artifact={"path": "x", "sha256": "0", "bytes": 1}), Ctx(Store(tmp_path)))


# -- door checks: whatever producer wrote the scans, the solver refuses or handles them with the reason --

@pytest.fixture(scope="module")
def captured():
    sim = SimulatedFlatbed("sim", bed_mm=(100, 100), seed=8)
    sim.place(demo_surface(20, 150, seed=3), centre_mm=(50, 50))
    res = capture_fragment(sim, "F0200", operator=simulated_operator(sim), dpi=150, prescan_dpi=25)
    res.scans["back"] = []
    return res


def _job_with(store, captured, change):
    import copy
    res = copy.deepcopy(captured)
    change(res.scans["front"])
    ref = write_scans(store, "F0200", res)
    return new_message("fragment.ready", fragment="F0200", artifact=ref)


def _no_rgbn(tmp_path):
    return not list(tmp_path.glob("fragments/*/rgbn/*.h5"))


def _set(scans, k, image, depth=None):
    s = scans[k]
    scans[k] = type(s)(image, s.dpi, s.rotation, s.area_mm, depth or s.depth)


@pytest.mark.parametrize("case, expected", [
    ("two scans", "front face has 2 scan\\(s\\): normals need at least 3"),
    ("8-bit values in 16 bits", "front scan 2: a 16-bit scan holding 8-bit values"),
    ("blank scan 0", "front scan 0: (blank|all black)"),
    ("float out of range", "front scan 1: float samples span"),
])
def test_bad_scans_are_rejected_naming_the_scan_and_nothing_is_written(tmp_path, captured, case, expected):
    from common.store import ArtifactError
    store = Store(tmp_path)

    def change(scans):
        if case == "two scans":
            del scans[2:]
        elif case == "8-bit values in 16 bits":
            _set(scans, 2, (scans[2].image // 257).astype(np.uint16))
        elif case == "blank scan 0":
            _set(scans, 0, np.full_like(scans[0].image, 9000))
        else:
            _set(scans, 1, scans[1].image.astype(np.float32) / 30000.0, depth=16)
    with pytest.raises(ArtifactError, match=expected):
        solver.handle(_job_with(store, captured, change), Ctx(store))
    assert _no_rgbn(tmp_path)


@pytest.mark.parametrize("case", ["grey", "float"])
def test_grey_and_float_scans_are_handled(tmp_path, captured, case):
    store = Store(tmp_path)

    def change(scans):
        for k, s in enumerate(scans):
            img = s.image.mean(axis=2).astype(np.uint16) if case == "grey" else s.image.astype(np.float32) / 65535
            _set(scans, k, img)
    events = solver.handle(_job_with(store, captured, change), Ctx(store))
    img = load_rgbn(store, events[0]["artifact"])
    assert img.has_normals and img.mask.sum() > 1000
    assert (img.normals[img.mask][:, 2] > 0.5).mean() > 0.95


def test_a_face_with_no_fragment_pixel_is_never_written_or_announced(tmp_path):
    from common.store import ArtifactError
    store = Store(tmp_path)
    sim = SimulatedFlatbed("sim", bed_mm=(100, 100), seed=9)
    from common.acquisition.capture import CaptureResult, Scan
    empty = sim.scan((20, 20, 60, 60), 150)            # the lid only: textured, not blank, no fragment
    res = CaptureResult("F0300", "sim", {"front": [Scan(empty, 150.0, 0, (20, 20, 60, 60), 16)]}, colour_only=True)
    job = new_message("fragment.ready", fragment="F0300", artifact=write_scans(store, "F0300", res))
    with pytest.raises(ArtifactError, match="no fragment pixel"):
        solver.handle(job, Ctx(store))
    assert _no_rgbn(tmp_path)
