"""Scanner backends behind one interface (§3.3.4).

Every backend offers ``name``, ``bed_mm = (width, height)`` and
``scan(area_mm, dpi, depth) -> (H, W, 3) uint8 | uint16`` where ``area_mm = (left, top, right,
bottom)`` in millimetres on the glass (None = whole bed). Backends:

* :class:`SaneScanner` — a real scanner through SANE (python-sane), 8/16-bit colour via the
  array API. SANE status errors become :class:`~common.acquisition.errors.ScannerError` with a
  message the operator can act on.
* :class:`~common.acquisition.flatbed_sim.SimulatedFlatbed` — the physically based simulator.
* :func:`list_usb_scanners` lists attached USB imaging devices (pyusb) for the operator.

SANE's ``test`` backend is off in a stock ``/etc/sane.d/dll.conf``; :func:`sane_test_config`
makes a private config directory that enables it (``SANE_CONFIG_DIR``) without touching /etc.
"""

from __future__ import annotations

import os
import tempfile
from typing import Protocol, runtime_checkable

import numpy as np

from common.acquisition.errors import ScannerError


@runtime_checkable
class Scanner(Protocol):
    name: str
    bed_mm: tuple[float, float]

    def scan(self, area_mm=None, dpi: float = 600, depth: int = 16) -> np.ndarray: ...


# SANE status text (as raised by python-sane) -> (status name, what the operator should do)
_SANE_STATUS = {
    "document feeder jammed": ("SANE_STATUS_JAMMED", "The scanner reports a paper jam. Open it, remove anything stuck, close it and press Retry."),
    "scanner cover is open": ("SANE_STATUS_COVER_OPEN", "The scanner lid is open. Close the lid gently over the fragment and press Retry."),
    "device busy": ("SANE_STATUS_DEVICE_BUSY", "The scanner is busy (another program may be using it). Wait a moment, close other scanning programs and press Retry."),
    "document feeder out of documents": ("SANE_STATUS_NO_DOCS", "The scanner is set to its document feeder. Switch the source to Flatbed and press Retry."),
    "error during device i/o": ("SANE_STATUS_IO_ERROR", "The scanner stopped responding. Check its USB cable and power, then press Retry."),
    "out of memory": ("SANE_STATUS_NO_MEM", "The computer ran out of memory for this scan. Close other programs or scan at a lower resolution."),
    "access to resource has been denied": ("SANE_STATUS_ACCESS_DENIED", "This computer account may not use the scanner. Ask the station administrator to add it to the 'scanner' group."),
    "operation was cancelled": ("SANE_STATUS_CANCELLED", "The scan was cancelled. Press Retry to scan again."),
    "invalid argument": ("SANE_STATUS_INVAL", "The scanner refused the scan settings (area or resolution). Check the station configuration."),
    "operation not supported": ("SANE_STATUS_UNSUPPORTED", "The scanner does not support this scan mode (colour, 8/16 bit). Check the station configuration."),
}


def sane_error(exc: BaseException, context: str = "scan") -> ScannerError:
    """Turn a python-sane error into a :class:`ScannerError` with an operator message."""
    text = str(exc).strip()
    status, advice = _SANE_STATUS.get(text.lower(), ("unknown", f"The scanner reported: {text}. Check it and press Retry."))
    return ScannerError(f"SANE {context} failed: {text} ({status})", advice, status=status)


def sane_test_config(directory: str | None = None) -> str:
    """Write a SANE config directory enabling only the ``test`` backend; return its path.

    Set ``SANE_CONFIG_DIR`` to it before the first :func:`sane.init` of the process.
    """
    directory = directory or tempfile.mkdtemp(prefix="tessera-sane-")
    with open(os.path.join(directory, "dll.conf"), "w") as fh:
        fh.write("test\n")
    return directory


class SaneScanner:
    """A real scanner through SANE.

    Parameters
    ----------
    device : str
        SANE device name (``sane.get_devices()``), e.g. ``epson2:libusb:001:004`` or ``test:0``.
    options : dict
        Extra SANE options to set once (e.g. ``{"source": "Flatbed"}``).
    """

    def __init__(self, device: str, options: dict | None = None):
        try:
            import sane
        except ImportError as exc:  # pragma: no cover - python-sane is a dependency
            raise ScannerError("python-sane is not installed", "Scanner support is not installed on this computer.") from exc
        self._sane = sane
        sane.init()
        try:
            self._dev = sane.open(device)
        except Exception as exc:
            raise sane_error(exc, f"open of {device!r}") from exc
        self.name = device
        self.options = dict(options or {})
        for k, v in self.options.items():
            setattr(self._dev, k.replace("-", "_"), v)
        opts = {o[1]: o for o in self._dev.get_options()}
        br_x, br_y = opts.get("br-x"), opts.get("br-y")
        self.bed_mm = (float(br_x[8][1]) if br_x else 216.0, float(br_y[8][1]) if br_y else 297.0)
        self._depths = list(opts["depth"][8]) if "depth" in opts and isinstance(opts["depth"][8], list) else [8]

    def scan(self, area_mm=None, dpi: float = 600, depth: int = 16) -> np.ndarray:
        """Scan ``area_mm`` (left, top, right, bottom mm) in colour; (H, W, 3) uint8/uint16."""
        if depth not in (8, 16):
            raise ValueError(f"depth must be 8 or 16, got {depth}")
        if depth not in self._depths:
            raise ScannerError(f"{self.name} does not scan at {depth} bit (offers {self._depths})",
                               f"This scanner cannot scan at {depth} bit; set the station to {max(self._depths)} bit.",
                               status="SANE_STATUS_UNSUPPORTED")
        x0, y0, x1, y1 = area_mm if area_mm is not None else (0, 0) + tuple(self.bed_mm)
        if not (0 <= x0 < x1 and 0 <= y0 < y1):
            raise ValueError(f"area_mm must be (left, top, right, bottom) with left<right, top<bottom, got {area_mm}")
        d = self._dev
        try:
            d.mode = "Color"
            d.depth = depth
            d.resolution = int(round(dpi))
            d.tl_x, d.tl_y, d.br_x, d.br_y = float(x0), float(y0), float(x1), float(y1)
            arr = d.arr_scan()
        except ScannerError:
            raise
        except Exception as exc:
            raise sane_error(exc) from exc
        arr = np.asarray(arr)
        if arr.ndim == 2:
            arr = np.repeat(arr[..., None], 3, axis=2)
        return arr.astype(np.uint16 if depth == 16 else np.uint8, copy=False)

    def close(self) -> None:
        self._dev.close()


def list_sane_devices() -> list[tuple[str, str, str, str]]:
    """SANE devices as (name, vendor, model, type)."""
    import sane
    sane.init()
    return list(sane.get_devices())


def list_usb_scanners() -> list[dict]:
    """Attached USB devices that look like scanners (imaging class 6 or vendor-specific ones from
    common scanner makers), as dicts ``{vendor_id, product_id, bus, address, product}``."""
    try:
        import usb.core
    except ImportError:  # pragma: no cover
        return []
    makers = {0x04B8: "Epson", 0x04A9: "Canon", 0x03F0: "HP", 0x04F9: "Brother", 0x07B3: "Plustek", 0x04C5: "Fujitsu"}
    found = []
    try:
        devices = list(usb.core.find(find_all=True))
    except Exception:  # no USB backend (e.g. no libusb in a container)
        return []
    for dev in devices:
        classes = {dev.bDeviceClass}
        try:
            for cfg in dev:
                classes |= {intf.bInterfaceClass for intf in cfg}
        except Exception:
            pass
        if 6 in classes or (dev.idVendor in makers and 0xFF in classes):
            try:
                product = dev.product
            except Exception:
                product = None
            found.append({"vendor_id": dev.idVendor, "product_id": dev.idProduct, "bus": dev.bus,
                          "address": dev.address, "product": product or makers.get(dev.idVendor, "unknown")})
    return found
