"""Tests of the scanner backends (common/acquisition/scanners.py) against SANE's ``test`` backend."""

import os

import numpy as np
import pytest

from common.acquisition.errors import ScannerError
from common.acquisition.flatbed_sim import SimulatedFlatbed
from common.acquisition.scanners import SaneScanner, Scanner, sane_error, sane_test_config


@pytest.fixture(scope="module")
def sane_test_device(tmp_path_factory):
    sane = pytest.importorskip("sane", reason="python-sane not installed")
    previous = os.environ.get("SANE_CONFIG_DIR")
    # enable only SANE's test backend, without touching /etc/sane.d (read at sane.init)
    os.environ["SANE_CONFIG_DIR"] = sane_test_config(str(tmp_path_factory.mktemp("sane")))
    try:
        try:
            sane.init()
            names = [d[0] for d in sane.get_devices()]
        except Exception as exc:   # pragma: no cover - depends on the machine
            pytest.skip(f"SANE unavailable: {exc}")
        if "test:0" not in names:
            pytest.skip("SANE test backend not available (install libsane1/sane-utils)")
        dev = SaneScanner("test:0", options={"test_picture": "Color pattern"})
        yield dev
        dev.close()
    finally:
        if previous is None:
            os.environ.pop("SANE_CONFIG_DIR", None)
        else:
            os.environ["SANE_CONFIG_DIR"] = previous


def test_sane_test_backend_scans_16_bit_colour_of_the_requested_area(sane_test_device):
    img = sane_test_device.scan((0, 0, 50.8, 25.4), dpi=100, depth=16)
    assert img.dtype == np.uint16 and img.ndim == 3 and img.shape[2] == 3
    assert abs(img.shape[1] - 200) <= 2 and abs(img.shape[0] - 100) <= 2     # 2 × 1 inch at 100 dpi
    assert img.max() > 255                                                   # really 16-bit values
    img8 = sane_test_device.scan((0, 0, 25.4, 25.4), dpi=50, depth=8)
    assert img8.dtype == np.uint8 and abs(img8.shape[0] - 50) <= 2


@pytest.mark.parametrize("status,words", [("SANE_STATUS_JAMMED", "jam"), ("SANE_STATUS_COVER_OPEN", "lid"),
                                          ("SANE_STATUS_DEVICE_BUSY", "busy"), ("SANE_STATUS_NO_DOCS", "Flatbed")])
def test_sane_error_statuses_become_operator_messages(sane_test_device, status, words):
    sane_test_device._dev.read_return_value = status
    try:
        with pytest.raises(ScannerError) as err:
            sane_test_device.scan((0, 0, 10, 10), dpi=50, depth=8)
    finally:
        sane_test_device._dev.read_return_value = "Default"
    assert err.value.status == status
    assert words in err.value.operator_message and "Retry" in err.value.operator_message


def test_unknown_sane_device_is_a_scanner_error(sane_test_device):
    with pytest.raises(ScannerError, match="open"):
        SaneScanner("test:99")


def test_unrecognised_sane_text_still_gives_a_message():
    err = sane_error(RuntimeError("Lamp failure"))
    assert err.status == "unknown" and "Lamp failure" in err.operator_message


def test_simulator_satisfies_the_scanner_interface():
    assert isinstance(SimulatedFlatbed(), Scanner)


def test_usb_listing_keeps_imaging_devices_only(monkeypatch):
    usb_core = pytest.importorskip("usb.core")

    class Intf:
        def __init__(self, cls):
            self.bInterfaceClass = cls

    class Dev:
        def __init__(self, vendor, product_id, cls, product):
            self.idVendor, self.idProduct, self.bDeviceClass = vendor, product_id, 0
            self.bus, self.address, self.product = 1, product_id, product
            self._cls = cls

        def __iter__(self):
            return iter([[Intf(self._cls)]])

    devices = [Dev(0x04B8, 0x013A, 0xFF, "Perfection V600"),   # Epson, vendor-specific: a scanner
               Dev(0x046D, 0xC077, 3, "USB mouse"),             # HID: not a scanner
               Dev(0x1234, 0x0001, 6, "Still imaging device")]  # imaging class
    monkeypatch.setattr(usb_core, "find", lambda find_all=True: devices)
    from common.acquisition.scanners import list_usb_scanners
    found = list_usb_scanners()
    assert [d["product"] for d in found] == ["Perfection V600", "Still imaging device"]
