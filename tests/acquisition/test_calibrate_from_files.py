"""Tests of ``tessera calibrate --from-files`` (services/cli/calibrate.py, common/acquisition/calibration.py).

The target scans are written by the simulated flatbed, whose lamp lies on the image's top side
(light from +y); the manifest's tilt-direction convention is checked against it.
"""

import csv
import json
import struct
import zlib

import cv2
import numpy as np
import pytest

from common.acquisition.calibration import (fit_lamp_model, lamp_at_depth, newest_calibration, read_target,
                                            target_normal)
from common.acquisition.flatbed_sim import SimulatedFlatbed, calibration_target, lamp_irradiance
from common.store import Store
from services.cli import main

AREA = (50.0, 50.0, 70.0, 70.0)
DPI = 150
POSES = [(0.0, 0.0)] + [(t, a) for t in (10.0, 20.0) for a in (0.0, 90.0, 180.0, 270.0)]


def _scan(sim, tilt, direction, crop=False, dpi=DPI):
    sim.place(calibration_target(tilt, direction, size_mm=4.0, dpi=300), angle_deg=0.0, centre_mm=(60, 60))
    img = sim.scan(AREA, dpi)
    if crop:      # the target alone, no ring of bed
        n = img.shape[0]
        img = img[n // 2 - 5:n // 2 + 5, n // 2 - 5:n // 2 + 5]
    return img


def _declare_dpi(path, dpi):
    """Splice a PNG pHYs chunk (pixels per metre) before the image data, as a scanner writes it."""
    data = path.read_bytes()
    i = data.index(b"IDAT") - 4
    ppm = round(dpi / 0.0254)
    body = struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", len(body)) + b"pHYs" + body + struct.pack(">I", zlib.crc32(b"pHYs" + body))
    path.write_bytes(data[:i] + chunk + data[i:])


def _write_targets(folder, sim, poses=POSES, grey=False, clip=(), crop=False, dpi=DPI, declare=None):
    """Target scans at ``dpi`` and their manifest; ``declare`` (one dpi, or one per pose) goes into the files."""
    rows = []
    for k, (t, a) in enumerate(poses):
        img = _scan(sim, t, a, crop=crop, dpi=dpi)
        if k in clip:
            img = np.clip(img.astype(np.float64) * 3.0, 0, 65535).astype(np.uint16)
        name = f"t{t:g}_d{a:g}.png"
        cv2.imwrite(str(folder / name), img.mean(axis=2).astype(np.uint16) if grey else img[..., ::-1])
        if declare is not None:
            _declare_dpi(folder / name, declare[k] if isinstance(declare, list) else declare)
        rows.append((name, t, a))
    manifest = folder / "targets.csv"
    with open(manifest, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "tilt_deg", "tilt_direction_deg"])
        w.writerows(rows)
    return manifest


def test_tilt_direction_convention_matches_the_simulator():
    # the simulator's lamp is on the image's top side: a target whose normal leans towards the image's
    # top (direction 90, counter-clockwise from +x on screen) faces the lamp and reads brighter than one
    # leaning towards the bottom (270); left and right (180, 0) read alike
    sim = SimulatedFlatbed("conv", bed_mm=(120, 120), seed=1, dust=0)
    v = {a: read_target(_scan(sim, 20.0, a), DPI).value for a in (0.0, 90.0, 180.0, 270.0)}
    assert v[90.0] > v[270.0] * 1.1
    assert v[0.0] == pytest.approx(v[180.0], rel=0.02)


@pytest.mark.parametrize("depth_mm", [0.0, 0.75])
def test_from_files_recovers_the_simulated_lamp_at_the_face_depth(tmp_path, depth_mm):
    # independent expectation: the simulator's own irradiance for these normals at that height above the glass
    sim = SimulatedFlatbed("sim-files", bed_mm=(120, 120), seed=2, dust=0)
    normals = np.array([target_normal(t, a) for t, a in POSES])
    truth = fit_lamp_model(normals, sim.exposure * lamp_irradiance(normals, depth_mm, sim.lamp))
    manifest = _write_targets(tmp_path, sim)
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-a", "--dpi", str(DPI), "--face-depth-mm", str(depth_mm)]) == 0
    cal, _ = newest_calibration(Store(store), "bench-a")
    assert np.allclose(cal.a, truth, atol=0.015), (cal.a, truth)
    assert cal.a[1] > 0.1          # light from the image's top = +y of the normal frame
    assert len(cal.report) == len(POSES) and all(e["used"] for e in cal.report)
    assert cal.fit_rms < 0.01


def test_from_files_measures_how_the_lamp_changes_with_the_distance_from_the_glass(tmp_path):
    # independent expectation: the simulator's own irradiance for these normals at 0 and 1.5 mm from the
    # glass (its lamp dims with distance); the targets' readings along their tilt measure that change
    sim = SimulatedFlatbed("sim-depth", bed_mm=(120, 120), seed=3, dust=0)
    normals = np.array([target_normal(t, a) for t, a in POSES])
    check = np.array([target_normal(t, a) for t in (0.0, 10.0, 20.0) for a in range(0, 360, 30)])   # calibrated range
    truth = {d: sim.exposure * lamp_irradiance(check, d, sim.lamp) for d in (0.0, 1.5)}
    assert np.abs(truth[1.5] - truth[0.0]).max() > 0.015          # the effect is there to be measured
    manifest = _write_targets(tmp_path, sim)
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-d", "--dpi", str(DPI), "--face-depth-mm", "0.75"]) == 0
    cal, _ = newest_calibration(Store(store), "bench-d")       # stored and read back
    assert cal.a_depth_mm == pytest.approx(0.75)
    X = np.c_[check, np.ones(len(check))]
    for d in (0.0, 1.5):     # the readings the model predicts (a_z and a_w alone are ill-conditioned at small tilts)
        err = np.abs(X @ lamp_at_depth(cal, d) - truth[d])
        assert err.max() < 0.008, (d, err.max())   # the first-order model itself misfits this lamp by 0.005
    # the change per mm of distance, reading by reading
    slope_true = (truth[1.5] - truth[0.0]) / 1.5
    slope = X @ cal.a_per_mm
    assert np.abs(slope - slope_true).max() < 0.3 * np.abs(slope_true).max()
    assert np.corrcoef(slope, slope_true)[0, 1] > 0.9
    assert all(e["slope_per_mm"] is not None for e in cal.report if e["tilt_deg"] > 0)


def test_clipped_target_scans_are_dropped_and_reported_per_file(tmp_path, capsys):
    sim = SimulatedFlatbed("sim-clip", bed_mm=(120, 120), seed=4, dust=0)
    manifest = _write_targets(tmp_path, sim, clip=(2, 6))
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-b", "--dpi", str(DPI)]) == 0
    out = capsys.readouterr().out
    assert out.count("DROPPED") == 2 and "2 dropped (clipped)" in out
    cal, _ = newest_calibration(Store(store), "bench-b")
    dropped = [e for e in cal.report if not e["used"]]
    assert [e["name"] for e in dropped] == ["t10_d90.png", "t20_d90.png"]
    assert all(e["clipped"] > 0.01 * e["pixels"] for e in dropped)
    assert all(e["clipped"] == 0 for e in cal.report if e["used"])
    assert cal.a[1] > 0.1 and cal.fit_rms < 0.01


def test_grey_files_and_tight_crops_of_the_target_are_accepted(tmp_path):
    sim = SimulatedFlatbed("sim-grey", bed_mm=(120, 120), seed=5, dust=0)
    manifest = _write_targets(tmp_path, sim, grey=True, crop=True)
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-c", "--dpi", str(DPI)]) == 0
    cal, _ = newest_calibration(Store(store), "bench-c")
    assert all(e["whole_image"] for e in cal.report)
    assert cal.a[1] > 0.1


@pytest.mark.parametrize("problem", ["missing column", "missing file", "truncated file", "too few"])
def test_bad_manifest_or_files_are_refused_and_nothing_is_stored(tmp_path, capsys, problem):
    sim = SimulatedFlatbed("sim-bad", bed_mm=(120, 120), seed=6, dust=0)
    manifest = _write_targets(tmp_path, sim, poses=POSES[:5] if problem == "too few" else POSES)
    text = manifest.read_text()
    if problem == "missing column":
        manifest.write_text(text.replace("tilt_direction_deg", "azimuth"))
    elif problem == "missing file":
        (tmp_path / "t10_d90.png").unlink()
    elif problem == "truncated file":
        p = tmp_path / "t10_d90.png"
        p.write_bytes(p.read_bytes()[:-200])
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-d", "--dpi", str(DPI)]) == 1
    cap = capsys.readouterr()
    expected = {"missing column": "tilt_direction_deg", "missing file": "t10_d90.png",
                "truncated file": "t10_d90.png", "too few": "at least 6"}[problem]
    # the error is on the standard error, the standard output (for results) says nothing of it
    assert "calibration failed" in cap.err and expected in cap.err
    assert "calibration failed" not in cap.out
    assert not (store / "calibration").exists() or not any((store / "calibration").rglob("*.h5"))


def test_from_files_needs_a_device_name(tmp_path, capsys):
    assert main(["calibrate", "--set", f'storage.root="{tmp_path}"', "--from-files", "x.csv"]) == 2
    cap = capsys.readouterr()
    assert cap.err.startswith("tessera calibrate: --from-files needs --device NAME") and cap.out == ""


def test_show_finds_a_from_files_calibration_by_its_device_name(tmp_path, capsys):
    # `tessera import scans --device NAME` uses the calibration stored under NAME; `--show --device
    # NAME` shows that one, as `--show --name NAME` does (it was refused: "--device must be simulated or sane")
    sim = SimulatedFlatbed("sim-show", bed_mm=(120, 120), seed=2, dust=0)
    manifest = _write_targets(tmp_path, sim)
    root = f'storage.root="{tmp_path / "store"}"'
    assert main(["calibrate", "--set", root, "--from-files", str(manifest), "--device", "epson-v850",
                 "--dpi", str(DPI)]) == 0
    capsys.readouterr()
    assert main(["calibrate", "--set", root, "--show", "--device", "epson-v850"]) == 0
    by_device = json.loads(capsys.readouterr().out)
    assert by_device["scanner"] == "epson-v850" and by_device["path"].startswith("calibration/epson-v850/")
    assert main(["calibrate", "--set", root, "--show", "--name", "epson-v850"]) == 0
    assert json.loads(capsys.readouterr().out) == by_device
    # a name with no calibration says which and how to make one
    assert main(["calibrate", "--set", root, "--show", "--device", "other-flatbed"]) == 1
    cap = capsys.readouterr()
    assert "'other-flatbed'" in cap.err and "--from-files MANIFEST --device other-flatbed" in cap.err
    assert cap.out == ""   # nothing a script reading --show's JSON could take for it
    # --show prints; it does not also calibrate
    assert main(["calibrate", "--set", root, "--show", "--from-files", str(manifest), "--device", "x"]) == 2
    cap = capsys.readouterr()
    assert "does not go with --from-files" in cap.err and cap.out == ""


def test_from_files_takes_the_dpi_the_files_declare(tmp_path):
    # docs/flatbed.md: without --dpi the scale is what the files declare; the lamp's change per mm
    # along the tilt is then measured in real millimetres (a silent 150 dpi halved them at 300 dpi)
    sim = SimulatedFlatbed("sim-declared", bed_mm=(120, 120), seed=3, dust=0)
    check = np.array([target_normal(t, a) for t in (0.0, 10.0, 20.0) for a in range(0, 360, 30)])
    slope_true = sim.exposure * (lamp_irradiance(check, 1.5, sim.lamp) - lamp_irradiance(check, 0.0, sim.lamp)) / 1.5
    manifest = _write_targets(tmp_path, sim, dpi=300, declare=300)
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-300"]) == 0
    cal, _ = newest_calibration(Store(store), "bench-300")
    assert cal.dpi == pytest.approx(300, abs=0.01)
    slope = np.c_[check, np.ones(len(check))] @ cal.a_per_mm
    assert np.abs(slope - slope_true).max() < 0.3 * np.abs(slope_true).max()


@pytest.mark.parametrize("declare", [None, [150.0] * 4 + [300.0] * 5])
def test_from_files_without_dpi_is_refused_when_the_files_declare_none_or_disagree(tmp_path, capsys, declare):
    sim = SimulatedFlatbed("sim-nodpi", bed_mm=(120, 120), seed=3, dust=0)
    manifest = _write_targets(tmp_path, sim, declare=declare)
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-e"]) == 2
    cap = capsys.readouterr()
    assert ("no dpi: the files declare none" if declare is None else "declare different resolutions") in cap.err
    assert "give --dpi" in cap.err and "give --dpi" not in cap.out
    assert not (store / "calibration").exists() or not any((store / "calibration").rglob("*.h5"))


def test_from_files_given_dpi_wins_over_the_files_with_a_warning(tmp_path, capsys):
    sim = SimulatedFlatbed("sim-given", bed_mm=(120, 120), seed=3, dust=0)
    manifest = _write_targets(tmp_path, sim, declare=72)      # an image editor's "don't know"
    store = tmp_path / "store"
    assert main(["calibrate", "--set", f'storage.root="{store}"', "--from-files", str(manifest),
                 "--device", "bench-f", "--dpi", str(DPI)]) == 0
    assert "declares 72.01 dpi but 150 dpi was given; using 150" in capsys.readouterr().err   # 2835 px/m
    cal, _ = newest_calibration(Store(store), "bench-f")
    assert cal.dpi == DPI
