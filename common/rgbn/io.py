"""RGBN images from and to common files: normal maps, albedo images, 8/16-bit PNG and TIFF.

Normal maps store ``n`` as colour ``(n + 1) / 2`` scaled to the integer range. The **OpenGL**
convention has green = +y up (Tessera's own convention); **DirectX** has green = +y down, so its
y is negated on reading. A pixel whose decoded vector is far from unit length (e.g. the black
background of many maps) or whose alpha is 0 is outside the mask.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from common.rgbn.image import RGBNImage
from common.store import write_file

import logging

log = logging.getLogger(__name__)

CONVENTIONS = ("opengl", "directx")
#: A decoded normal map is refused when fewer than this share of its pixels are unit vectors
#: (length within 15 %) ...
MIN_UNIT_SHARE = 0.6
#: ... or more than this share point away from the viewer (nz < -0.05).
MAX_BACKFACING_SHARE = 0.05
_TIFF = (".tif", ".tiff")


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float32; one array of the input's size
    is made, the rest is computed in place: the linear segment's values are made for its pixels
    only, the darkest few, and put back after the power)."""
    arr = np.asarray(values, dtype=np.float32)
    out = np.clip(np.atleast_1d(arr), 0.0, 1.0, out=np.empty(np.atleast_1d(arr).shape, np.float32))  # C order
    low = np.flatnonzero(out.reshape(-1) <= 0.04045)
    dark = out.reshape(-1)[low] / np.float32(12.92)
    out += np.float32(0.055)
    out /= np.float32(1.055)
    _power(out, 2.4)
    out.reshape(-1)[low] = dark
    return out.reshape(arr.shape)


def _power(values: np.ndarray, exponent: float) -> np.ndarray:
    """``values ** exponent`` in place for float32 values >= 0: OpenCV's vectorised power (3x
    numpy's on this machine; equal to 2e-7) on a C-contiguous array, numpy's on any other layout
    (where a flat view does not exist: reshaping would copy, and the power would be lost)."""
    import cv2

    if not values.flags.c_contiguous:
        return np.power(values, np.float32(exponent), out=values)
    flat = values.reshape(-1, 1)   # a view: OpenCV takes it as one column
    cv2.pow(flat, float(exponent), dst=flat)
    return values


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values in [0, 1] (float32; two arrays of the input's
    size are made, the rest is computed in place)."""
    arr = np.asarray(values, dtype=np.float32)
    v = np.clip(np.atleast_1d(arr), 0.0, 1.0)
    out = _power(v.copy(), 1 / 2.4)
    out *= np.float32(1.055)
    out -= np.float32(0.055)
    low = v <= 0.0031308
    v *= np.float32(12.92)
    np.copyto(out, v, where=low)
    return out.reshape(arr.shape)


def _read_raw(path: Path) -> tuple[np.ndarray, float]:
    """Image as (H, W[, C]) in file channel order RGB(A), plus its integer full scale (1.0 for floats).

    Read through the door checks every image path in Tessera uses
    (:func:`common.imports.door.read_image_checked`): a missing, truncated or corrupt file, an
    unsupported sample type or 8-bit values in a 16-bit file are refused (``ImportRefused``, a
    ``ValueError``) naming the file. Uniform images are accepted: a flat normal map or a plain
    albedo is a valid input here.
    """
    from common.imports.door import read_image_checked

    if not path.is_file():
        raise FileNotFoundError(f"image {path} does not exist")
    img = read_image_checked(path, allow_blank=True)
    return img.pixels, float(img.full_scale)


def read_normal_map(path, convention: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Read a normal map (8/16-bit PNG/TIFF, or float .npy/.tif holding the vectors themselves).

    Parameters
    ----------
    path : path
        The file. Integer images are decoded as ``n = 2 v / full_scale - 1``; float images are
        taken as the vectors themselves.
    convention : {'auto', 'opengl', 'directx'}
        OpenGL: green is y up (Tessera's convention). DirectX: green is y down (negated here).
        'auto' decides by the integrability of the two readings (:func:`detect_convention`) and
        logs the evidence.

    Returns
    -------
    normals : (H, W, 3) float32
        Unit normals, x right, y up, z to viewer (``(0, 0, 1)`` outside the mask).
    mask : (H, W) bool
        Valid pixels: alpha > 0 if there is an alpha channel, and decoded length in [0.5, 1.5].

    Raises
    ------
    ValueError
        When the image is not plausibly a normal map (fewer than 60 % unit vectors, or more than
        5 % pointing away from the viewer — a photograph, say), naming the file and the reason.
    """
    if convention not in CONVENTIONS + ("auto",):
        raise ValueError(f"convention must be one of {CONVENTIONS + ('auto',)}, got {convention!r}")
    path = Path(path)
    arr, full = _read_raw(path)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"normal map {path} must have 3 or 4 channels, got shape {arr.shape}")
    alpha = arr[..., 3] > 0 if arr.shape[2] == 4 else None
    # an all-black pixel is the background of many maps, not a vector
    carrying = np.any(arr[..., :3] != 0, axis=2)
    alpha = carrying if alpha is None else alpha & carrying
    v = arr[..., :3].astype(np.float32)
    if full != 1.0:
        v = v * np.float32(2.0 / full) - 1.0
    length = np.sqrt(np.einsum("...i,...i->...", v, v))
    check_normal_map(v, length, alpha, name=str(path))
    mask = (length > 0.5) & (length < 1.5) & np.isfinite(length)
    if alpha is not None:
        mask &= alpha
    normals = np.zeros_like(v)
    normals[..., 2] = 1.0
    normals[mask] = v[mask] / length[mask][:, None]
    if convention == "auto":
        convention, evidence = detect_convention(normals, mask)
        log.info("normal map %s: %s convention (%s)", path, convention, evidence)
    if convention == "directx":
        normals[..., 1] = -normals[..., 1]
    return normals, mask


def check_normal_map(v: np.ndarray, length: np.ndarray | None = None, alpha: np.ndarray | None = None, *,
                     name: str = "normal map") -> None:
    """Refuse decoded vectors that are not plausibly a normal map, with the reason.

    A normal map stores unit vectors facing the viewer: at least :data:`MIN_UNIT_SHARE` of the
    pixels inside ``alpha`` (the caller leaves an all-black background out) must have a length within 15 %
    of 1, and at most :data:`MAX_BACKFACING_SHARE` may have nz < -0.05. A photograph decoded as
    ``2 v - 1`` fails one or both (its grey pixels give vectors along (1, 1, 1) of any length).
    """
    if length is None:
        length = np.sqrt(np.einsum("...i,...i->...", v, v))
    use = np.isfinite(length) & (length > 0.05)  # a zero vector carries nothing
    if alpha is not None:
        use &= alpha
    n = int(use.sum())
    if n == 0:
        return  # all background: an empty mask, nothing to judge
    unit = float(np.mean(np.abs(length[use] - 1.0) < 0.15))
    back = float(np.mean(v[..., 2][use] < -0.05 * length[use]))
    if unit < MIN_UNIT_SHARE:
        raise ValueError(f"{name} does not look like a normal map: only {100 * unit:.0f} % of its pixels decode "
                         f"to unit vectors (a normal map has nearly all; >= {100 * MIN_UNIT_SHARE:.0f} % needed) "
                         "— is it a photograph or an albedo?")
    if back > MAX_BACKFACING_SHARE:
        raise ValueError(f"{name} does not look like a normal map: {100 * back:.0f} % of its pixels point away "
                         f"from the viewer (blue < 0.5; at most {100 * MAX_BACKFACING_SHARE:.0f} % allowed)")


def detect_convention(normals: np.ndarray, mask: np.ndarray | None = None, *,
                      sigma_px: float = 2.0) -> tuple[str, dict]:
    """Tell an OpenGL (green = y up) from a DirectX (green = y down) normal map read as OpenGL,
    by integrability: the normals of a real surface are the gradient of a height, so the curl
    of the gradient field ``(p, q) = (-nx / nz, -ny / nz)``, ``dp/dy - dq/dx``, vanishes; read
    with the wrong y sign, ``q`` changes sign and the curl becomes ``dp/dy + dq/dx``, which does
    not. The reading with the smaller median |curl| wins.

    Returns
    -------
    convention : 'opengl' or 'directx'
        How the given normals (decoded as OpenGL) were really stored; 'opengl' when the test
        cannot decide (ratio < 1.2: a surface without relief in both directions).
    evidence : dict
        ``curl_opengl``, ``curl_directx`` (median |curl| per pixel) and their ``ratio``.

    References
    ----------
    R. Frankot, R. Chellappa, "A method for enforcing integrability in shape from shading
    algorithms", IEEE PAMI 10(4), 1988.
    """
    import cv2

    from common.rgbn._filters import gaussian_blur

    n = np.asarray(normals, np.float32)
    m = np.ones(n.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if sigma_px > 0:
        n = gaussian_blur(n, sigma_px)
    nz = np.maximum(n[..., 2], 0.2)
    p = -n[..., 0] / nz
    q = -n[..., 1] / nz
    # y up: d/dy = -d/drow
    dp_dy = -cv2.Sobel(p, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    dq_dx = cv2.Sobel(q, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    use = cv2.erode(m.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    use &= n[..., 2] > 0.3
    if use.sum() < 100:
        return "opengl", {"curl_opengl": None, "curl_directx": None, "ratio": None, "note": "too few pixels"}
    gl = float(np.median(np.abs(dp_dy - dq_dx)[use]))
    dx = float(np.median(np.abs(dp_dy + dq_dx)[use]))
    ratio = max(gl, dx) / max(min(gl, dx), 1e-12)
    evidence = {"curl_opengl": round(gl, 6), "curl_directx": round(dx, 6), "ratio": round(ratio, 2)}
    if ratio < 1.2:
        evidence["note"] = "undecided, assuming opengl"
        return "opengl", evidence
    return ("opengl" if gl <= dx else "directx"), evidence


def read_albedo(path, *, srgb: bool | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a colour image as linear albedo in [0, 1].

    ``srgb`` None decodes integer images as sRGB (photographs) and leaves float images linear.
    Returns ``(albedo (H, W, 3) float32, alpha mask or None)``.
    """
    path = Path(path)
    arr, full = _read_raw(path)
    alpha = None
    if arr.ndim == 3 and arr.shape[2] in (2, 4):
        alpha = arr[..., -1] > 0
        arr = arr[..., :-1]
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=2)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"albedo image {path} must be grey or RGB, got shape {arr.shape}")
    v = arr.astype(np.float32) / np.float32(full)
    if srgb is None:
        srgb = full != 1.0
    return (srgb_to_linear(v) if srgb else np.clip(v, 0, 1).astype(np.float32)), alpha


def load_rgbn_files(normals_path, albedo_path=None, *, convention: str = "auto", dpi: float = 300.0,
                    srgb: bool | None = None) -> RGBNImage:
    """An :class:`RGBNImage` from a normal map file plus an optional albedo image.

    Without an albedo the fragment is a uniform light grey (0.8). ``dpi`` sets the physical scale
    (curvatures in 1/mm); say so when it is a nominal value.
    """
    normals, mask = read_normal_map(normals_path, convention)
    if albedo_path is None:
        albedo = np.full(normals.shape, 0.8, np.float32)
    else:
        albedo, alpha = read_albedo(albedo_path, srgb=srgb)
        if albedo.shape[:2] != normals.shape[:2]:
            raise ValueError(f"albedo {albedo_path} is {albedo.shape[1]}x{albedo.shape[0]} px but the normal map "
                             f"{normals_path} is {normals.shape[1]}x{normals.shape[0]}: they must share a pixel grid")
        if alpha is not None:
            mask &= alpha
    return RGBNImage(albedo=albedo, mask=mask, dpi=dpi, normals=normals)


def write_image(path, image: np.ndarray, *, bits: int = 8, alpha: np.ndarray | None = None,
                dpi: float | None = None) -> Path:
    """Write an (H, W) or (H, W, 3) image with values in [0, 1] as 8/16-bit PNG or TIFF.

    Values are written as given (no colour encoding); ``alpha`` (H, W) in [0, 1] adds a channel;
    ``dpi``, when given, is declared in the file (PNG ``pHYs``, TIFF resolution in inches), so other
    tools measure the picture in mm.
    The format follows the suffix: ``.png``, ``.tif``/``.tiff``. The file is encoded in memory
    (:func:`encode_png`, :func:`encode_tiff`) and written by :func:`common.store.write_file`: the
    free space checked first, an older file at ``path`` replaced only by a whole new one, with the
    mode the umask allows. Raises :class:`common.store.StorageFull` (an OSError) naming ``path``
    when the disk is full.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in _TIFF:
        data = encode_tiff(image, bits=bits, alpha=alpha, dpi=dpi)
    elif suffix == ".png":
        data = encode_png(image, bits=bits, alpha=alpha, dpi=dpi)
    else:
        raise ValueError(f"output {path} must end in .png, .tif or .tiff")
    write_file(path, data, public=True)
    return path


def encode_png(image: np.ndarray, *, bits: int = 8, alpha: np.ndarray | None = None,
               dpi: float | None = None) -> bytes:
    """The bytes :func:`write_image` writes to a ``.png`` file, in memory (to size a write before making it);
    ``dpi`` given: declared in a ``pHYs`` chunk (pixels per metre).

    Examples
    --------
    >>> png = encode_png(np.zeros((4, 6, 3)), bits=16, alpha=np.ones((4, 6)))
    >>> png[:8] == b"\\x89PNG\\r\\n\\x1a\\n", cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).shape
    (True, (4, 6, 4))
    """
    data = _image_samples(image, bits, alpha)
    if data.ndim == 3:
        data = cv2.cvtColor(data, cv2.COLOR_RGBA2BGRA if data.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", data)
    if not ok:
        raise ValueError(f"could not encode a {data.shape} image as PNG")
    return buf.tobytes() if dpi is None else _with_png_dpi(buf.tobytes(), dpi)


def _with_png_dpi(png: bytes, dpi: float) -> bytes:
    """PNG bytes with a ``pHYs`` chunk (pixels per metre, unit metre) declaring ``dpi``, put after ``IHDR``."""
    import struct
    import zlib

    if not (np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi!r}")
    ppm = int(round(float(dpi) / 0.0254))
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    end = 8 + 8 + 13 + 4                         # signature, IHDR's length and type, its 13 bytes, its CRC
    if png[12:16] != b"IHDR":
        raise ValueError("not a PNG starting with IHDR")
    return png[:end] + chunk + png[end:]


def encode_tiff(image: np.ndarray, *, bits: int = 16, alpha: np.ndarray | None = None,
                dpi: float | None = None) -> bytes:
    """The bytes :func:`write_image` writes to a ``.tif`` file (zlib-compressed), in memory; ``dpi``
    given: declared as ``XResolution``/``YResolution`` in inches.

    Examples
    --------
    >>> import tifffile, io
    >>> tif = encode_tiff(np.zeros((4, 6, 3)), bits=16, alpha=np.ones((4, 6)))
    >>> tifffile.imread(io.BytesIO(tif)).shape
    (4, 6, 4)
    """
    import io

    import tifffile

    data = _image_samples(image, bits, alpha)
    buf = io.BytesIO()
    if dpi is not None and not (np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi!r}")
    resolution = {} if dpi is None else {"resolution": (float(dpi), float(dpi)), "resolutionunit": "INCH"}
    tifffile.imwrite(buf, data, photometric="rgb" if data.ndim == 3 else "minisblack",
                     compression="zlib", extrasamples=["unassalpha"] if alpha is not None else None, **resolution)
    return buf.getvalue()


def _image_samples(image: np.ndarray, bits: int, alpha: np.ndarray | None) -> np.ndarray:
    """(H, W) or (H, W, 3|4) uint8/uint16 samples of an image in [0, 1] (and its alpha) at ``bits``."""
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    img = np.asarray(image)
    if img.dtype.kind not in "ui":
        img = img.astype(np.float32, copy=False)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
    data = to_bits(img, bits)
    if alpha is not None:
        alpha = to_bits(np.asarray(alpha), bits)
        if alpha.shape != img.shape[:2]:
            raise ValueError(f"alpha must be {img.shape[:2]}, got {alpha.shape}")
        if data.ndim == 2:
            data = np.repeat(data[..., None], 3, axis=2)
        data = np.concatenate([data, alpha[..., None]], axis=2)
    return data


def to_bits(values: np.ndarray, bits: int) -> np.ndarray:
    """Display values as uint8 / uint16: floats in [0, 1] are scaled and rounded; integer arrays
    (an image drawn in tiles is already 8/16-bit) are rescaled only if their depth differs."""
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    v = np.asarray(values)
    want = np.uint8 if bits == 8 else np.uint16
    if v.dtype == want:
        return v
    if v.dtype == np.uint8:
        return (v.astype(np.uint16) * 257).astype(want)
    if v.dtype == np.uint16:
        return ((v.astype(np.uint32) + 128) // 257).astype(want)
    full = 255.0 if bits == 8 else 65535.0
    return np.round(np.clip(np.nan_to_num(v.astype(np.float32, copy=False)), 0.0, 1.0) * full).astype(want)


def encode_normal_map(normals: np.ndarray, mask: np.ndarray | None = None, convention: str = "opengl") -> np.ndarray:
    """Normals as colour ``(n + 1) / 2`` in [0, 1] (for :func:`write_image`); 0 outside ``mask``."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    n = np.asarray(normals, dtype=np.float32).copy()
    if convention == "directx":
        n[..., 1] = -n[..., 1]
    out = (n + 1.0) * 0.5
    if mask is not None:
        out[~np.asarray(mask, bool)] = 0.0
    return out
