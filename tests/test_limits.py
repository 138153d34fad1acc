"""Sane ranges at stage entry: dpi, image size and fragment extent are checked from the declared
shapes and attributes, before any pixel is read."""

from __future__ import annotations

import time

import h5py
import numpy as np
import pytest

from common.limits import (DPI_RANGE, MAX_EXTENT_MM, MAX_IMAGE_PIXELS, check_dpi, check_image_size,
                           check_rgbn_file, check_scans_file)
from common.store import ArtifactError


@pytest.mark.parametrize("dpi", [0.001, 0.0, -300.0, 1e9, float("nan"), float("inf"), "abc"])
def test_dpi_outside_the_flatbed_range_is_rejected_naming_the_value(dpi):
    with pytest.raises(ArtifactError, match="dpi"):
        check_dpi(dpi, "scan")


def test_dpi_at_the_ends_of_the_range_is_accepted():
    assert check_dpi(DPI_RANGE[0], "scan") == DPI_RANGE[0]
    assert check_dpi(np.float64(DPI_RANGE[1]), "scan") == DPI_RANGE[1]


def test_image_size_limits_pixels_extent_and_emptiness():
    check_image_size((2000, 3000, 3), 300.0, "face")  # 17 × 25 cm at 300 dpi: fine
    with pytest.raises(ArtifactError, match="200000×200000"):
        check_image_size((200_000, 200_000, 3), 4800.0, "face")
    side = int(MAX_EXTENT_MM / 25.4 * 100) + 2   # just over a metre at 100 dpi, few pixels
    assert side * side < MAX_IMAGE_PIXELS
    with pytest.raises(ArtifactError, match="mm across"):
        check_image_size((10, side), 100.0, "face")
    with pytest.raises(ArtifactError, match="empty"):
        check_image_size((0, 64), 100.0, "face")
    with pytest.raises(ArtifactError, match="not an image"):
        check_image_size((64,), 100.0, "face")


def test_declared_huge_rgbn_is_rejected_without_reading_it(tmp_path):
    path = tmp_path / "huge.h5"
    with h5py.File(path, "w") as f:
        f.attrs["dpi"] = 100.0
        f.create_dataset("albedo", shape=(200_000, 200_000, 3), dtype=np.float32, chunks=(64, 64, 3))
        f.create_dataset("mask", shape=(200_000, 200_000), dtype=bool, chunks=(64, 64))
    assert path.stat().st_size < 1_000_000
    t0 = time.perf_counter()
    with h5py.File(path, "r") as f, pytest.raises(ArtifactError, match="200000×200000"):
        check_rgbn_file(f)
    assert time.perf_counter() - t0 < 5.0   # reading 480 GB would take hours (or the machine's memory)


def test_rgbn_file_at_plausible_scale_passes_and_bad_dpi_names_the_value(tmp_path):
    path = tmp_path / "face.h5"
    with h5py.File(path, "w") as f:
        f.attrs["dpi"] = 300.0
        f["albedo"] = np.zeros((32, 48, 3), np.float32)
        f["mask"] = np.ones((32, 48), bool)
    with h5py.File(path, "r") as f:
        check_rgbn_file(f)
    with h5py.File(path, "r+") as f:
        f.attrs["dpi"] = 1e9
    with h5py.File(path, "r") as f, pytest.raises(ArtifactError, match=r"dpi 1e\+09"):
        check_rgbn_file(f)


def test_scans_file_checks_every_scan_and_its_area(tmp_path):
    path = tmp_path / "scans.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("front")
        for k in range(2):
            d = g.create_dataset(f"scan_{k}", data=np.zeros((20, 30, 3), np.uint16))
            d.attrs.update(dpi=100.0, area_mm=np.array([0.0, 0.0, 7.62, 5.08]))
        f.create_group("back")
    with h5py.File(path, "r") as f:
        check_scans_file(f)
    with h5py.File(path, "r+") as f:
        f["front/scan_1"].attrs["dpi"] = 0.001
    with h5py.File(path, "r") as f, pytest.raises(ArtifactError, match=r"front/scan_1: dpi 0.001"):
        check_scans_file(f)
    with h5py.File(path, "r+") as f:
        f["front/scan_1"].attrs["dpi"] = 100.0
        f["front/scan_0"].attrs["area_mm"] = np.array([0.0, 0.0, 5000.0, 10.0])
    with h5py.File(path, "r") as f, pytest.raises(ArtifactError, match="scan area"):
        check_scans_file(f)
