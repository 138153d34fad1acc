"""Checks at the door: an image file is decoded completely, or refused with the reason.

OpenCV decodes a truncated PNG or JPEG without an error: the missing rows come back grey (or
black), and a photometric solve or a mask made from them is silently wrong. Every importer
therefore reads its images through :func:`read_image_checked`, which

* recognises the format by its signature (PNG, JPEG, TIFF; ``.npy`` float arrays),
* checks the file is complete before decoding: a PNG's chunks must all fit in the file and end
  with ``IEND`` with correct CRCs; a JPEG is decoded by Pillow with truncated images refused (its
  entropy-coded data must reach the end-of-image marker); a TIFF's strips or tiles must lie inside
  the file,
* checks the declared size against :data:`common.limits.MAX_IMAGE_PIXELS` before decoding,
* checks the sample type (8/16-bit integers or float), a declared bit depth (and 8-bit values
  stored in a 16-bit file), the number of channels, and refuses all-black images (hot pixels
  aside: up to :data:`HOT_SAMPLES_FRACTION` of the samples may be bright) and blank (uniform) images.

Each refusal is an :class:`~common.imports.driver.ImportRefused` whose message starts with the
file's path.
"""

from __future__ import annotations

import os
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from common.imports.driver import ImportRefused
from common.limits import MAX_IMAGE_PIXELS

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_TIFF_SIGS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")

#: An image with no more than ``HOT_SAMPLES_FRACTION`` of its samples at or above this fraction
#: of full scale is "all black".
BLACK_FRACTION = 2.0 / 255.0
#: Bright samples a black frame may hold (hot or stuck sensor pixels): a robust 99.9th percentile,
#: so a handful of hot pixels does not make a frame taken with the lamp off look lit.
HOT_SAMPLES_FRACTION = 0.001
#: An image whose samples all lie within this fraction of full scale of each other is "blank".
BLANK_FRACTION = 2.0 / 255.0


@dataclass
class CheckedImage:
    """A fully decoded image that passed the door checks.

    Attributes
    ----------
    pixels : (H, W) or (H, W, C) ndarray
        Samples as stored (uint8, uint16 or float32), channels in RGB(A) order.
    full_scale : float
        255, 65535 or 1.0 (float images).
    bits : int
        8, 16 or 32 (float).
    format : str
        ``png``, ``jpeg``, ``tiff`` or ``npy``.
    path : Path
    """

    pixels: np.ndarray
    full_scale: float
    bits: int
    format: str
    path: Path

    @property
    def channels(self) -> int:
        return 1 if self.pixels.ndim == 2 else int(self.pixels.shape[2])

    def as_float(self) -> np.ndarray:
        """Samples scaled to [0, 1] as float32 (no colour decoding)."""
        return self.pixels.astype(np.float32) / np.float32(self.full_scale)


def _refuse(path, reason: str) -> ImportRefused:
    return ImportRefused(f"{path}: {reason}")


def _sniff(path: Path, head: bytes) -> str:
    if head.startswith(_PNG_SIG):
        return "png"
    if head.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if head[:4] in _TIFF_SIGS:
        return "tiff"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    raise _refuse(path, "is not a PNG, JPEG, TIFF or .npy image (unknown file signature)")


def image_format(path: str | os.PathLike) -> str | None:
    """The format a file's signature names, ``png``, ``jpeg``, ``tiff`` or ``npy``, without decoding it.

    None for a file that is missing, unreadable or of another format: :func:`read_image_checked`
    refuses those with the reason. For warnings before an import (``tessera import scans`` warns
    that JPEG, 8-bit and lossy, adds noise to the normals).

    Examples
    --------
    >>> import tempfile, cv2, numpy as np
    >>> p = tempfile.mktemp(suffix=".jpg")
    >>> _ = cv2.imwrite(p, np.zeros((8, 8), np.uint8))
    >>> image_format(p)
    'jpeg'
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
        return _sniff(path, head)
    except (OSError, ImportRefused):
        return None


def _check_png(path: Path) -> tuple[int, int]:
    """Walk the chunks: each must fit in the file with a correct CRC, ending with IEND. (width, height)."""
    size = path.stat().st_size
    width = height = None
    with open(path, "rb") as fh:
        fh.seek(8)
        pos = 8
        while True:
            header = fh.read(8)
            if len(header) < 8:
                raise _refuse(path, f"is truncated (PNG ends after {pos} of its bytes without the IEND chunk)")
            length, ctype = struct.unpack(">I4s", header)
            if pos + 12 + length > size:
                raise _refuse(path, f"is truncated (PNG chunk {ctype.decode('latin-1')!r} at byte {pos} needs "
                                    f"{length} bytes, the file ends at {size})")
            data = fh.read(length)
            crc = struct.unpack(">I", fh.read(4))[0]
            if zlib.crc32(ctype + data) & 0xFFFFFFFF != crc:
                raise _refuse(path, f"is corrupt (PNG chunk {ctype.decode('latin-1')!r} at byte {pos} fails its CRC)")
            if ctype == b"IHDR":
                width, height = struct.unpack(">II", data[:8])
            if ctype == b"IEND":
                break
            pos += 12 + length
    if width is None:
        raise _refuse(path, "is corrupt (PNG without an IHDR header)")
    return width, height


def _check_size(path: Path, width: int, height: int) -> None:
    if width * height > MAX_IMAGE_PIXELS:
        raise _refuse(path, f"declares {width}x{height} pixels, more than the limit of "
                            f"{MAX_IMAGE_PIXELS / 1e6:.0f} Mpx")


def _cv2_read(path: Path) -> np.ndarray:
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise _refuse(path, "could not be decoded")
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGBA if arr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return arr


def _decode(path: Path, fmt: str) -> np.ndarray:
    if fmt == "png":
        _check_size(path, *_check_png(path))
        return _cv2_read(path)
    if fmt == "jpeg":
        from PIL import Image, ImageFile
        ImageFile.LOAD_TRUNCATED_IMAGES = False
        try:
            with Image.open(path) as im:
                _check_size(path, *im.size)
                im.load()
                if im.mode not in ("L", "RGB"):
                    im = im.convert("RGB")
                return np.asarray(im)
        except ImportRefused:
            raise
        except (OSError, SyntaxError, ValueError) as exc:
            reason = "is truncated" if "truncated" in str(exc).lower() else "could not be decoded as JPEG"
            raise _refuse(path, f"{reason} ({exc})") from None
    if fmt == "tiff":
        import tifffile
        try:
            with tifffile.TiffFile(path) as tf:
                page = tf.pages[0]
                _check_size(path, int(page.imagewidth), int(page.imagelength))
                size = path.stat().st_size
                offsets, counts = page.dataoffsets, page.databytecounts
                if any(o + c > size for o, c in zip(offsets, counts)) or (counts and not all(counts)):
                    raise _refuse(path, f"is truncated (TIFF image data runs past the end of the {size}-byte file)")
                try:
                    arr = page.asarray()
                except ValueError as exc:  # a compression tifffile has no codec for here (LZW without imagecodecs)
                    if "imagecodecs" not in str(exc):
                        raise
                    arr = _cv2_read(path)
        except ImportRefused:
            raise
        except Exception as exc:  # tifffile raises several types for damaged files
            raise _refuse(path, f"could not be decoded as TIFF ({type(exc).__name__}: {exc})") from None
        if arr.ndim == 3 and arr.shape[0] in (3, 4) and arr.shape[2] not in (3, 4):
            arr = np.moveaxis(arr, 0, 2)  # planar TIFF
        return arr
    from numpy.lib import format as npy
    try:
        with open(path, "rb") as fh:   # the declared shape first, as for the other formats
            major, _ = npy.read_magic(fh)
            shape = (npy.read_array_header_1_0 if major == 1 else npy.read_array_header_2_0)(fh)[0]
        if len(shape) >= 2:
            _check_size(path, int(shape[1]), int(shape[0]))
        arr = np.load(path, allow_pickle=False)
    except ImportRefused:
        raise
    except (OSError, ValueError) as exc:
        raise _refuse(path, f"could not be read as .npy ({exc})") from None
    return arr


def read_image_checked(path: str | os.PathLike, *, bits: int | None = None,
                       channels: Sequence[int] = (1, 2, 3, 4), allow_blank: bool = False) -> CheckedImage:
    """Read one image file completely, or refuse it with the reason.

    Parameters
    ----------
    path : path
        PNG (8/16-bit), JPEG (8-bit), TIFF (8/16-bit or float) or ``.npy`` (float).
    bits : {8, 16}, optional
        Declared bit depth: the file must have it. A 16-bit file whose samples never exceed 255
        (8-bit values written into a 16-bit container) is refused whatever ``bits`` says.
    channels : sequence of int
        Channel counts accepted (1 grey, 2 grey + alpha, 3 RGB, 4 RGBA).
    allow_blank : bool
        Accept all-black or uniform images (masks, for instance).

    Returns
    -------
    CheckedImage

    Raises
    ------
    ImportRefused
        The message starts with the path: missing, empty, unknown format, truncated, corrupt,
        unsupported sample type, wrong bit depth, wrong channel count, all black, blank.

    Examples
    --------
    >>> import tempfile, cv2, numpy as np
    >>> p = tempfile.mktemp(suffix=".png")
    >>> _ = cv2.imwrite(p, np.tile(np.arange(64, dtype=np.uint8), (8, 1)))
    >>> read_image_checked(p).pixels.shape
    (8, 64)
    """
    if bits not in (None, 8, 16):
        raise ValueError(f"bits must be 8, 16 or None, got {bits!r}")
    path = Path(path)
    if not path.is_file():
        raise _refuse(path, "does not exist" if not path.exists() else "is not a file")
    if path.stat().st_size == 0:
        raise _refuse(path, "is empty (0 bytes)")
    with open(path, "rb") as fh:
        head = fh.read(16)
    fmt = _sniff(path, head)
    arr = _decode(path, fmt)
    if arr.dtype == np.uint8:
        full, nbits = 255.0, 8
    elif arr.dtype == np.uint16:
        full, nbits = 65535.0, 16
    elif arr.dtype in (np.float32, np.float64):
        arr, full, nbits = arr.astype(np.float32), 1.0, 32
    else:
        raise _refuse(path, f"has samples of type {arr.dtype}; 8/16-bit integers or float are supported")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    n_ch = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else -1)
    if arr.ndim not in (2, 3) or n_ch not in tuple(channels):
        want = ", ".join(map(str, channels))
        raise _refuse(path, f"has shape {arr.shape} ({n_ch} channels); expected {want} channels")
    if min(arr.shape[:2]) < 1:
        raise _refuse(path, f"has no pixels (shape {arr.shape})")
    if nbits == 32 and not np.isfinite(arr).all():
        raise _refuse(path, "holds NaN or infinite samples")
    if bits is not None and nbits != bits:
        raise _refuse(path, f"is {nbits}-bit but {bits}-bit was declared")
    colour = arr if n_ch in (1, 3) else arr[..., :-1]
    if n_ch in (2, 4):  # judge the colour where the alpha channel shows something
        shown = arr[..., -1] > 0
        if not shown.any() and not allow_blank:
            raise _refuse(path, "is fully transparent (alpha 0 everywhere)")
        colour = colour[shown] if shown.any() else colour
    hi, lo = float(colour.max()), float(colour.min())
    if nbits == 16 and hi <= 255 and hi > 0:
        raise _refuse(path, f"is a 16-bit file holding 8-bit values (largest sample {hi:.0f} of 65535): "
                            "export it again at 16 bits, or as 8-bit")
    if not allow_blank:
        lit = int(np.count_nonzero(colour >= BLACK_FRACTION * full)) if hi >= BLACK_FRACTION * full else 0
        if lit <= HOT_SAMPLES_FRACTION * colour.size:
            raise _refuse(path, f"is all black ({lit} of {colour.size} samples at or above "
                                f"{BLACK_FRACTION * 100:.1f} % of full scale, no more than hot pixels would make): "
                                "lamp off or lid closed?")
        if hi - lo < BLANK_FRACTION * full:
            raise _refuse(path, f"is blank (every sample within {BLANK_FRACTION * 100:.1f} % of {lo / full:.3f} "
                                "of full scale)")
    return CheckedImage(arr, full, nbits, fmt, path)


def read_images_checked(paths: Sequence[str | os.PathLike], *, bits: int | None = None,
                        channels: Sequence[int] = (1, 2, 3, 4), allow_blank: bool = False,
                        workers: int | None = None) -> list[CheckedImage]:
    """:func:`read_image_checked` on every path (decoded in parallel threads); sizes must agree.

    ``workers`` threads (default: the number of CPUs, at most 8); the decoders release the GIL.
    Raises :class:`ImportRefused` for the first bad file in the order given, or naming the first
    file whose size differs from the first one's.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("paths is empty: give at least one image")
    n = workers or min(8, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=max(1, n)) as pool:
        futures = [pool.submit(read_image_checked, p, bits=bits, channels=channels, allow_blank=allow_blank)
                   for p in paths]
        images = [f.result() for f in futures]
    h, w = images[0].pixels.shape[:2]
    for im in images[1:]:
        if im.pixels.shape[:2] != (h, w):
            raise _refuse(im.path, f"is {im.pixels.shape[1]}x{im.pixels.shape[0]} px but {paths[0].name} is "
                                   f"{w}x{h}: all images must have the same size")
    return images
