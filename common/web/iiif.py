"""IIIF Image API 3.0 (compliance level 2, plus mirroring, upscaling, the gray and bitonal qualities
and the profile and canonical link headers) over the cached tile pyramids, and IIIF Presentation
API 3.0 manifests of fragments.

Image requests are ``{region}/{size}/{rotation}/{quality}.{format}`` (IIIF Image API 3.0 §4):

* region: ``full``, ``square``, ``x,y,w,h`` (pixels), ``pct:x,y,w,h``; a region reaching past the
  image is cut to it, one entirely outside is an error;
* size: ``max``, ``w,``, ``,h``, ``w,h``, ``!w,h`` (fit inside, never larger than the region),
  ``pct:n``; with a leading ``^`` the result may be larger than the region (upscaling), without it
  that is an error; every size is limited by :data:`MAX_AREA` (``max`` is shrunk to fit, ``^max``
  is the region scaled to that area, §4.2);
* rotation: ``0``, ``90``, ``180``, ``270`` (clockwise), with a leading ``!`` mirrored first
  (left-right), ``360`` is ``0``; quality ``default`` (= ``color``), ``color``, ``gray`` or
  ``bitonal``; format ``jpg`` or ``png`` (PNG keeps the alpha channel: the fragment's coverage).

A request is served from the pyramid level whose resolution is the coarsest at or above the
requested one (:func:`pyramid_level_for`), cut from its tiles and area-resampled to the size.

References
----------
IIIF Image API 3.0, https://iiif.io/api/image/3.0/ ; IIIF Presentation API 3.0,
https://iiif.io/api/presentation/3.0/
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Callable, Mapping

import cv2
import numpy as np

#: largest output image, pixels (``maxArea`` of info.json)
MAX_AREA = 16 * 1024 * 1024
IMAGE_CONTEXT = "http://iiif.io/api/image/3/context.json"
#: the compliance level claimed, and its profile document (the ``Link: rel="profile"`` header, §6)
PROFILE = "level2"
PROFILE_URI = f"http://iiif.io/api/image/3/{PROFILE}.json"
PRESENTATION_CONTEXT = "http://iiif.io/api/presentation/3/context.json"
FORMATS = {"jpg": "image/jpeg", "png": "image/png"}
QUALITIES = ("default", "color", "gray", "bitonal")
ROTATIONS = (0, 90, 180, 270)
#: thumbnails in manifests fit in this square (pixels)
THUMBNAIL_PX = 256

_NUM = r"\d+(?:\.\d+)?"


class IIIFError(ValueError):
    """A request the server cannot answer; ``status`` is the HTTP status IIIF asks for (400, 501)."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class ImageRequest:
    """A parsed image request: the region in full-resolution pixels and the output size."""

    x: int
    y: int
    w: int
    h: int
    width: int
    height: int
    fmt: str
    rotation: int = 0
    mirror: bool = False
    quality: str = "default"


def parse_region(region: str, width: int, height: int) -> tuple[int, int, int, int]:
    """``(x, y, w, h)`` in pixels of an IIIF region (Image API 3.0 §4.2), cut to the image.

    Examples
    --------
    >>> parse_region("square", 400, 300)
    (50, 0, 300, 300)
    >>> parse_region("pct:50,50,100,100", 400, 300)
    (200, 150, 200, 150)
    """
    if region == "full":
        return 0, 0, width, height
    if region == "square":
        side = min(width, height)
        return (width - side) // 2, (height - side) // 2, side, side
    m = re.fullmatch(rf"(pct:)?({_NUM}),({_NUM}),({_NUM}),({_NUM})", region)
    if not m:
        raise IIIFError(f"region {region!r} is not full, square, x,y,w,h or pct:x,y,w,h")
    vals = [float(v) for v in m.groups()[1:]]
    if m.group(1):
        x, y = vals[0] * width / 100.0, vals[1] * height / 100.0
        w, h = vals[2] * width / 100.0, vals[3] * height / 100.0
        x, y, w, h = int(round(x)), int(round(y)), int(round(w)), int(round(h))
    else:
        if any(v != int(v) for v in vals):
            raise IIIFError(f"region {region!r}: pixel regions are whole numbers")
        x, y, w, h = (int(v) for v in vals)
    if w <= 0 or h <= 0:
        raise IIIFError(f"region {region!r} has no area")
    if x >= width or y >= height:
        raise IIIFError(f"region {region!r} lies outside the {width} x {height} image")
    return x, y, min(w, width - x), min(h, height - y)


def parse_size(size: str, w: int, h: int, *, max_area: int = MAX_AREA) -> tuple[int, int]:
    """Output ``(width, height)`` of an IIIF size (Image API 3.0 §4.3) for a ``w`` x ``h`` region.

    Examples
    --------
    >>> parse_size("100,", 400, 300)
    (100, 75)
    >>> parse_size("!100,100", 400, 300)
    (100, 75)
    """
    up = size.startswith("^")
    s = size[1:] if up else size
    aspect = w / h
    if s == "max":
        # max: the region, shrunk to MAX_AREA if larger; ^max: the region scaled to MAX_AREA (§4.2)
        if w * h <= max_area and not up:
            return w, h
        f = math.sqrt(max_area / (w * h))
        out = (max(1, int(w * f)), max(1, int(h * f)))
        while out[0] * out[1] > max_area:
            out = (max(1, out[0] - 1), max(1, int((out[0] - 1) / aspect)))
        return out
    m = re.fullmatch(rf"pct:({_NUM})", s)
    if m:
        p = float(m.group(1)) / 100.0
        out = (int(round(w * p)), int(round(h * p)))
    elif re.fullmatch(r"\d+,", s):
        ow = int(s[:-1])
        out = (ow, int(round(ow / aspect)))
    elif re.fullmatch(r",\d+", s):
        oh = int(s[1:])
        out = (int(round(oh * aspect)), oh)
    elif re.fullmatch(r"!\d+,\d+", s):
        # the largest size inside the box; without ^ also no larger than the region (§4.2: "as
        # large as possible but not larger than the extracted region, w or h")
        bw, bh = (int(v) for v in s[1:].split(","))
        f = min(bw / w, bh / h) if up else min(bw / w, bh / h, 1.0)
        out = (min(bw, int(round(w * f))), min(bh, int(round(h * f))))
    elif re.fullmatch(r"\d+,\d+", s):
        out = tuple(int(v) for v in s.split(","))
    else:
        raise IIIFError(f"size {size!r} is not max, w, ,h, w,h, !w,h or pct:n (with an optional ^)")
    ow, oh = max(1, out[0]), max(1, out[1])
    if out[0] <= 0 or out[1] <= 0:
        raise IIIFError(f"size {size!r} gives an empty image")
    if not up and (ow > w or oh > h):
        raise IIIFError(f"size {size!r} is larger than the {w} x {h} region: ask with ^ to upscale")
    if ow * oh > max_area:
        raise IIIFError(f"size {size!r} gives {ow} x {oh} pixels, more than {max_area}")
    return ow, oh


def parse_request(region: str, size: str, rotation: str, quality_format: str, width: int,
                  height: int) -> ImageRequest:
    """Parse the four path parts of an image request (rotation by 90s, optionally mirrored;
    default/color/gray/bitonal; jpg/png)."""
    mirror = rotation.startswith("!")
    m = re.fullmatch(rf"{_NUM}", rotation[1:] if mirror else rotation)
    degrees = float(m.group(0)) if m else -1.0
    degrees = 0.0 if degrees == 360.0 else degrees
    if degrees not in ROTATIONS:
        raise IIIFError(f"rotation {rotation!r} is not supported (0, 90, 180 or 270, optionally after !)", 400)
    quality, _, fmt = quality_format.rpartition(".")
    if quality not in QUALITIES:
        raise IIIFError(f"quality {quality!r} is not supported ({', '.join(QUALITIES)})")
    if fmt not in FORMATS:
        raise IIIFError(f"format {fmt!r} is not supported ({', '.join(FORMATS)})")
    x, y, w, h = parse_region(region, width, height)
    ow, oh = parse_size(size, w, h)
    return ImageRequest(x, y, w, h, ow, oh, fmt, int(degrees), mirror, quality)


def pyramid_level_for(req: ImageRequest, levels: int) -> int:
    """The coarsest pyramid level (0 = full resolution, level L is 2**L smaller) that still has at
    least the requested resolution in both directions."""
    scale = min(req.w / req.width, req.h / req.height)
    return max(0, min(levels - 1, int(math.floor(math.log2(scale))) if scale >= 1 else 0))


def render_request(req: ImageRequest, levels: list[Mapping], read: Callable[[int, int, int, int, int], np.ndarray]
                   ) -> np.ndarray:
    """The RGBA pixels of a request from a pyramid.

    ``levels``: ``pyramid.json``'s levels; ``read(level, y0, y1, x0, x1)`` returns that level's RGBA
    pixels (:meth:`common.web.tiles.TileCache.region`). The region is cut from
    :func:`pyramid_level_for`'s level (widened to whole cells of that level when it does not fall on
    them: at most one cell, ``2**level`` full-resolution pixels) and resampled to the size: area
    average when shrinking, bilinear when upscaling. At full resolution and full size the pixels
    are the tiles' own.
    """
    level = pyramid_level_for(req, len(levels))
    f = 2 ** level
    lv = levels[level]
    x0, y0 = req.x // f, req.y // f
    x1 = min(lv["width"], max(x0 + 1, -(-(req.x + req.w) // f)))
    y1 = min(lv["height"], max(y0 + 1, -(-(req.y + req.h) // f)))
    px = read(level, y0, y1, x0, x1)
    if (px.shape[1], px.shape[0]) == (req.width, req.height):
        return px
    shrink = px.shape[1] >= req.width and px.shape[0] >= req.height
    return cv2.resize(px, (req.width, req.height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def finish(rgba: np.ndarray, req: ImageRequest) -> np.ndarray:
    """The last steps of a request after the size (Image API 3.0 §4.4-4.5): mirror (left-right),
    rotate clockwise by ``req.rotation`` degrees, then the quality: ``gray`` is the ITU-R BT.601
    luma of the display values, ``bitonal`` that luma thresholded at mid-grey (black or white);
    alpha kept."""
    out = rgba[:, ::-1] if req.mirror else rgba
    out = np.rot90(out, k=-(req.rotation // 90)) if req.rotation else out
    if req.quality in ("gray", "bitonal"):
        luma = cv2.cvtColor(np.ascontiguousarray(out[..., :3]), cv2.COLOR_RGB2GRAY)
        if req.quality == "bitonal":
            luma = np.where(luma >= 128, 255, 0).astype(np.uint8)
        out = np.dstack([luma, luma, luma, out[..., 3]])
    return np.ascontiguousarray(out)


def canonical_path(req: ImageRequest, width: int, height: int) -> str:
    """The canonical ``region/size/rotation/quality.format`` of a request (Image API 3.0 §4.8), for
    the ``Link: rel="canonical"`` header: ``full`` or ``x,y,w,h``; ``max`` when the size is what
    ``max`` gives, ``^max`` when what ``^max`` gives, else ``w,h`` (``^w,h`` when upscaled); ``!`` and an integer; the quality."""
    region = "full" if (req.x, req.y, req.w, req.h) == (0, 0, width, height) else f"{req.x},{req.y},{req.w},{req.h}"
    if (req.width, req.height) == parse_size("max", req.w, req.h):
        size = "max"
    elif (req.width, req.height) == parse_size("^max", req.w, req.h):
        size = "^max"
    else:
        up = req.width > req.w or req.height > req.h
        size = f"{'^' if up else ''}{req.width},{req.height}"
    rotation = f"{'!' if req.mirror else ''}{req.rotation}"
    return f"{region}/{size}/{rotation}/{req.quality}.{req.fmt}"


def encode(rgba: np.ndarray, fmt: str, *, jpeg_quality: int = 90) -> bytes:
    """The bytes of an RGBA image as ``jpg`` (no alpha: RGB as is) or ``png`` (RGBA)."""
    if fmt == "png":
        ok, buf = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    elif fmt == "jpg":
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgba[..., :3], cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        raise IIIFError(f"format {fmt!r} is not supported ({', '.join(FORMATS)})")
    if not ok:
        raise IIIFError(f"could not encode a {rgba.shape} image as {fmt}", 500)
    return buf.tobytes()


def info_json(service_id: str, info: Mapping) -> dict:
    """The ``info.json`` (Image API 3.0 §5) of an image served from a pyramid (``pyramid.json``)."""
    levels = info["levels"]
    return {
        "@context": IMAGE_CONTEXT, "id": service_id, "type": "ImageService3",
        "protocol": "http://iiif.io/api/image", "profile": PROFILE,
        "width": info["width"], "height": info["height"], "maxArea": MAX_AREA,
        "sizes": [{"width": lv["width"], "height": lv["height"]} for lv in reversed(levels)
                  if lv["width"] * lv["height"] <= MAX_AREA],
        "tiles": [{"width": info["tile_px"], "height": info["tile_px"],
                   "scaleFactors": [2 ** lv["level"] for lv in levels]}],
        # every quality beyond default must be listed (§4.4), color too
        "extraQualities": ["color", "gray", "bitonal"],
        "extraFeatures": ["mirroring", "sizeUpscaling", "profileLinkHeader", "canonicalLinkHeader"],
        "preferredFormats": ["png", "jpg"],
    }


def manifest(base: str, fragment: str, faces: Mapping[str, Mapping], metadata: Mapping[str, str],
             *, homepage: str | None = None) -> dict:
    """A Presentation 3.0 manifest of a fragment: one canvas per face.

    Parameters
    ----------
    base : str
        URL of the station (``http://host:port``), no trailing slash.
    fragment : str
    faces : mapping
        ``{face: {"width", "height", "layers": [layer names, "albedo" first], "pixel_mm"}}``.
    metadata : mapping
        Label -> value pairs shown by viewers (inventory, find-spot, …).
    homepage : str, optional
        The fragment's page on the station.

    Canvases come front, back, then other faces by name (:func:`common.imports.export.face_order`:
    a viewer opens the first). Each canvas is
    painted with the albedo; renders are offered as a ``Choice``; the normal map is
    linked from the canvas as a ``rendering`` (PNG, OpenGL (n + 1) / 2) and its image service. Each
    canvas and the manifest (its first canvas's) have a ``thumbnail``: the albedo fitted in
    :data:`THUMBNAIL_PX` square (a Manifest SHOULD have one, Presentation 3.0 §3.2).
    """
    mid = f"{base}/iiif/presentation/{fragment}/manifest"
    canvases = []
    from common.imports.export import face_order

    for face, f in sorted(faces.items(), key=lambda kv: face_order(kv[0])):
        cid = f"{base}/iiif/presentation/{fragment}/canvas/{face}"

        def image(layer, fmt="jpg", size=None):
            """The layer as an Image with its service: whole (``max``), or at ``size`` (w, h)."""
            sid = f"{base}/iiif/image/{image_id(fragment, face, layer)}"
            w, h = size or (f["width"], f["height"])
            out = {"id": f"{sid}/full/{f'{w},{h}' if size else 'max'}/0/default.{fmt}", "type": "Image",
                   "format": FORMATS[fmt], "width": w, "height": h, "label": {"en": [layer]},
                   "service": [{"id": sid, "type": "ImageService3", "profile": PROFILE}]}
            if size:
                del out["label"]
            return out

        paintable = [layer for layer in f["layers"] if layer != "normals"]
        thumbnail = [image(paintable[0], size=parse_size(f"!{THUMBNAIL_PX},{THUMBNAIL_PX}", f["width"], f["height"]))]
        body = image(paintable[0]) if len(paintable) == 1 else {"type": "Choice",
                                                                "items": [image(layer) for layer in paintable]}
        canvas = {
            "id": cid, "type": "Canvas", "label": {"en": [f"{fragment} {face}"]},
            "width": f["width"], "height": f["height"], "thumbnail": thumbnail,
            "items": [{"id": f"{cid}/page", "type": "AnnotationPage", "items": [{
                "id": f"{cid}/page/painting", "type": "Annotation", "motivation": "painting", "body": body,
                "target": cid}]}],
        }
        if f.get("pixel_mm"):
            canvas["service"] = [{"id": f"{cid}#physical-scale", "type": "PhysicalDimensions",
                                  "profile": "http://iiif.io/api/annex/services/physdim",
                                  "physicalScale": f["pixel_mm"], "physicalUnits": "mm"}]
        if "normals" in f["layers"]:
            n = image("normals", "png")
            n["label"] = {"en": ["normal map: 8-bit RGB = (n + 1) / 2, OpenGL (x right, y up, z to the viewer); "
                                 "alpha = coverage"]}
            canvas["rendering"] = [n]
        canvases.append(canvas)
    out = {
        "@context": PRESENTATION_CONTEXT, "id": mid, "type": "Manifest", "label": {"none": [fragment]},
        "metadata": [{"label": {"en": [k]}, "value": {"none": [str(v)]}} for k, v in metadata.items() if v],
        "items": canvases,
    }
    if canvases:
        out["thumbnail"] = canvases[0]["thumbnail"]
    if homepage:
        out["homepage"] = [{"id": homepage, "type": "Text", "label": {"en": [f"Fragment {fragment}"]},
                            "format": "text/html"}]
    return out


def image_id(fragment: str, face: str, layer: str) -> str:
    """The IIIF identifier of one layer of one face: ``<fragment>~<face>~<layer>`` (``~`` is in no
    fragment id, face or layer name)."""
    return f"{fragment}~{face}~{layer}"


def split_image_id(identifier: str) -> tuple[str, str, str]:
    """Inverse of :func:`image_id`; IIIFError (404) for anything else."""
    parts = identifier.split("~")
    if len(parts) != 3 or not all(parts):
        raise IIIFError(f"no image {identifier!r} (identifiers are <fragment>~<face>~<layer>)", 404)
    return parts[0], parts[1], parts[2]
