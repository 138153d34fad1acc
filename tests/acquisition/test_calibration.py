"""Tests of the lamp calibration (common/acquisition/calibration.py)."""

import numpy as np
import pytest

from common.acquisition.calibration import (calibrate_scanner, cross_validate, fit_lamp_model, newest_calibration,
                                            save_calibration, simulated_target_operator, target_normal)
from common.acquisition.errors import CalibrationError
from common.acquisition.flatbed_sim import SimulatedFlatbed, calibration_target
from common.acquisition.locate import to_float
from common.store import Store


def _samples(a, quad=0.0, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    n = np.array([target_normal(t, p) for t in (0, 5, 10, 15, 20, 25) for p in range(0, 360, 45)])
    i = n @ a[:3] + a[3] + quad * n[:, 0] * n[:, 1] * 10 + rng.normal(0, noise, len(n))
    return n, i


def test_fit_recovers_known_coefficients_exactly():
    a = np.array([0.01, 0.3, 0.55, 0.2])
    n, i = _samples(a)
    np.testing.assert_allclose(fit_lamp_model(n, i), a, atol=1e-10)


def test_cross_validation_prefers_second_order_only_when_the_data_needs_it():
    a = np.array([0.0, 0.3, 0.55, 0.2])
    lin = cross_validate(*_samples(a, noise=0.002))
    assert lin["second"] >= 0.9 * lin["first"]               # no gain from the extra terms
    quad = cross_validate(*_samples(a, quad=0.05, noise=0.002))
    assert quad["second"] < 0.5 * quad["first"]


def test_fit_validates_its_input():
    with pytest.raises(ValueError, match="normals"):
        fit_lamp_model(np.zeros((5, 2)), np.zeros(5))
    with pytest.raises(ValueError, match="at least 4"):
        fit_lamp_model(np.zeros((3, 3)), np.zeros(3))


@pytest.fixture(scope="module")
def sim_calibration():
    sim = SimulatedFlatbed(bed_mm=(100, 100), seed=11)
    cal = calibrate_scanner(sim, simulated_target_operator(sim), area_mm=(50, 50, 70, 70))
    return sim, cal


def test_fitted_model_predicts_new_simulated_scans(sim_calibration):
    sim, cal = sim_calibration
    assert cal.cv_rmse["first"] < 0.01 and cal.order == 1     # first order suffices (§3.3.5)
    for tilt, az in ((12.0, 30.0), (22.0, 200.0), (7.0, 300.0)):
        sim.place(calibration_target(tilt, az, size_mm=8, dpi=150), angle_deg=0.0, centre_mm=(60, 60))
        img = to_float(sim.scan((56, 56, 64, 64), 150)).mean(axis=2)
        measured = float(np.median(img[20:27, 20:27])) / 0.8
        predicted = float(cal.predict(target_normal(tilt, az)[None])[0])
        assert predicted == pytest.approx(measured, rel=0.02), (tilt, az)


def test_lamp_side_is_image_top_in_the_fitted_model(sim_calibration):
    _, cal = sim_calibration
    assert cal.a[1] > 0.2 and abs(cal.a[0]) < 0.02       # light from +y (row 0), none along the lamp


def test_newest_valid_calibration_is_used_and_broken_ones_skipped(sim_calibration, tmp_path):
    _, cal = sim_calibration
    store = Store(tmp_path)
    with pytest.raises(CalibrationError, match="tessera calibrate"):
        newest_calibration(store, "sim")
    cal.date = "2026-01-01T00:00:00+00:00"
    old = save_calibration(store, cal)
    cal.date = "2026-03-01T00:00:00+00:00"
    new = save_calibration(store, cal)
    got, ref = newest_calibration(store, "sim")
    assert ref.path == new.path and got.date.startswith("2026-03-01")
    store.path(new.path).write_bytes(b"not hdf5")                # the newest is broken: fall back
    got, ref = newest_calibration(store, "sim")
    assert ref.path == old.path


def test_tessera_calibrate_stores_and_shows_the_simulated_scanners_model(tmp_path, capsys):
    from services.cli import main
    root = f'storage.root="{tmp_path}"'
    assert main(["calibrate", "--set", root, "--azimuths", "0,90,180,270", "--tilts", "0,10,20"]) == 0
    out = capsys.readouterr().out
    assert "leave-one-out RMS error" in out and "stored calibration/sim/" in out
    assert main(["calibrate", "--set", root, "--show"]) == 0
    shown = capsys.readouterr().out
    assert '"scanner": "sim"' in shown and '"a"' in shown


def test_calibrate_prints_its_progress_on_stderr_and_only_its_result_on_stdout(tmp_path, capsys):
    # the progress lines ("[ 20%] ... target at tilt ...") were printed on the standard output,
    # mixed into the report that scripts read
    from services.cli import main
    assert main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--azimuths", "0,90,180,270",
                 "--tilts", "0,10,20"]) == 0
    cap = capsys.readouterr()
    lines = cap.out.splitlines()
    assert len(lines) == 3, cap.out
    assert lines[0].startswith("scanner sim: a = (") and lines[1].startswith("leave-one-out RMS error")
    assert lines[2].startswith("stored calibration/sim/")
    progress = [ln for ln in cap.err.splitlines() if "target scans" in ln]
    assert len(progress) == 9                                    # tilt 0 once, 2 tilts x 4 rotations
    assert "9/9" in progress[-1] and "target at tilt 20°, rotation 270°" in progress[-1]


def test_show_of_a_nominal_calibration_is_strict_json(tmp_path, capsys):
    # a nominal calibration has no cross-validation: its cv_rmse is NaN, which --show printed as a bare NaN
    import json

    from services.cli import main
    root = f'storage.root="{tmp_path}"'
    assert main(["calibrate", "--set", root, "--nominal", "--lamp-direction-deg", "90", "--device", "flat-n"]) == 0
    capsys.readouterr()
    assert main(["calibrate", "--set", root, "--show", "--device", "flat-n"]) == 0

    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    shown = json.loads(capsys.readouterr().out, parse_constant=refuse)
    assert shown["scanner"] == "flat-n" and shown["cv_rmse"] == {"first": None, "second": None}


@pytest.mark.parametrize("argv, words, code", [
    (["--device", "epson-v850"], "--device must be simulated or sane", 2),
    (["--nominal", "--device", "flat-x"], "--nominal needs --lamp-direction-deg D", 2),
    (["--nominal", "--lamp-direction-deg", "0"], "--nominal needs --device NAME", 2),
])
def test_calibrate_errors_go_to_the_standard_error_with_a_failing_exit(tmp_path, capsys, argv, words, code):
    # the standard output is for results (the report, --show's JSON): an error printed there read as one
    from services.cli import main
    assert main(["calibrate", "--set", f'storage.root="{tmp_path}"', *argv]) == code
    cap = capsys.readouterr()
    assert cap.err.startswith(f"tessera calibrate: {words}") and cap.out == ""


def test_a_bad_tilt_list_is_named_on_stderr_as_the_command_names_its_errors(tmp_path, capsys):
    import pytest

    from services.cli import main

    with pytest.raises(SystemExit, match="^tessera calibrate: --tilts must be comma-separated numbers, got '0,ten'"):
        main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--tilts", "0,ten"])


@pytest.mark.parametrize("tilts, azimuths, says", [
    ("0,10", "0,90", "make 3 target pose(s)"),        # too few poses to fit and cross-validate
    ("0,95", "0,90,180,270", "[0, 90)"),             # a tilt no jig can hold
    ("0,10,-5", "0,90,180,270", "-5"),
])
def test_calibrate_refuses_target_poses_it_cannot_fit_before_scanning(tmp_path, capsys, tilts, azimuths, says):
    # too few poses ended in a ValueError traceback after the target had been scanned
    from services.cli import main
    assert main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--tilts", tilts, "--azimuths", azimuths]) == 2
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err.startswith("tessera calibrate: ") and says in cap.err
    assert "target scans" not in cap.err and not (tmp_path / "calibration").exists()


def test_a_real_scanners_operator_is_asked_on_stderr_so_stdout_stays_the_report(tmp_path, capsys, monkeypatch):
    """With a SANE scanner each target pose waits for the operator's Enter; its prompt was written by input() to the
    standard output, which holds only the report. The scanner here is the simulated one standing in for SANE
    (nobody moves its target, so the fit fails: only where the prompts go is checked)."""
    import io

    from common.acquisition.flatbed_sim import SimulatedFlatbed
    from services.cli import main

    monkeypatch.setattr("common.acquisition.scanners.SaneScanner", lambda device: SimulatedFlatbed("bench", seed=1))
    monkeypatch.setattr("sys.stdin", io.StringIO("\n" * 9))
    main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--device", "sane", "--azimuths", "0,90,180,270",
          "--tilts", "0,10,20"])
    cap = capsys.readouterr()
    assert "Set the calibration target at tilt 0° turned to 0°" in cap.err
    assert "Set the calibration target" not in cap.out


def test_a_closed_operator_input_during_calibration_stops_with_a_message_and_stores_nothing(tmp_path, capsys,
                                                                                            monkeypatch):
    """The operator's input is closed (a piped or detached session) when the first target pose is asked for: exit 1
    with a line naming it, no traceback, and no calibration written."""
    import io

    from common.acquisition.flatbed_sim import SimulatedFlatbed
    from services.cli import main

    monkeypatch.setattr("common.acquisition.scanners.SaneScanner", lambda device: SimulatedFlatbed("bench", seed=1))
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    rc = main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--device", "sane", "--azimuths", "0,90,180,270",
               "--tilts", "0,10,20"])
    cap = capsys.readouterr()
    assert rc == 1
    assert "operator's input closed" in cap.err and "no calibration stored" in cap.err
    assert "Traceback" not in cap.err
    assert not list(tmp_path.rglob("*.h5"))
