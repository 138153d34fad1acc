"""The RGBN image: colour plus a surface normal per pixel, and how it is stored.

Conventions used everywhere in Tessera
--------------------------------------
* Arrays are indexed ``[row, column]``; row 0 is the top of the image.
* Normals are unit vectors in the image frame: **x to the right (increasing column), y up
  (towards row 0), z out of the image towards the viewer** (the OpenGL normal-map and DiLiGenT
  convention). A flat fragment lying face up has n = (0, 0, 1).
* Albedo is linear reflectance in [0, 1], RGB.
* Physical size comes from ``dpi``: one pixel is ``25.4 / dpi`` millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import h5py
import numpy as np

from common.limits import check_rgbn_file
from common.store import ArtifactError, ArtifactRef, Store

SCHEMA = "tessera.rgbn"
SCHEMA_VERSION = 1


@dataclass
class RGBNImage:
    """One face of one fragment as colour + normals.

    Attributes
    ----------
    albedo : (H, W, 3) float32
        Linear RGB reflectance in [0, 1].
    mask : (H, W) bool
        True on the fragment.
    dpi : float
        Sampling density; pixel size in mm is ``25.4 / dpi``.
    normals : (H, W, 3) float32 or None
        Unit normals (x right, y up, z to viewer); None for colour-only data.
    confidence : (H, W) float32 or None
        Per-pixel reliability of the normal in [0, 1] (0 = shadowed/saturated/unsolved).
    discontinuity : (H, W, 2) float32 or None
        Depth-discontinuity map: direction (x right, y up) towards the occluding side, scaled
        by the discontinuity strength (flash capture, Raskar et al. 2004).
    height_mm : (H, W) float32 or None
        Height or thickness map in millimetres where one exists.
    """

    albedo: np.ndarray
    mask: np.ndarray
    dpi: float
    normals: np.ndarray | None = None
    confidence: np.ndarray | None = None
    discontinuity: np.ndarray | None = None
    height_mm: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        self.albedo = np.asarray(self.albedo, dtype=np.float32)
        if self.albedo.ndim == 2:
            self.albedo = np.repeat(self.albedo[..., None], 3, axis=2)
        if self.albedo.ndim != 3 or self.albedo.shape[2] != 3:
            raise ValueError(f"albedo must be (H, W, 3), got {self.albedo.shape}")
        shape = self.albedo.shape[:2]
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.mask.shape != shape:
            raise ValueError(f"mask must be {shape}, got {self.mask.shape}")
        if not np.isfinite(self.dpi) or self.dpi <= 0:
            raise ValueError(f"dpi must be a positive number, got {self.dpi}")
        self.dpi = float(self.dpi)
        for name, channels in (("normals", 3), ("discontinuity", 2), ("confidence", 0), ("height_mm", 0)):
            arr = getattr(self, name)
            if arr is None:
                continue
            arr = np.asarray(arr, dtype=np.float32)
            want = shape + ((channels,) if channels else ())
            if arr.shape != want:
                raise ValueError(f"{name} must be {want}, got {arr.shape}")
            setattr(self, name, arr)

    @property
    def shape(self) -> tuple[int, int]:
        return self.albedo.shape[:2]

    @property
    def pixel_mm(self) -> float:
        """Pixel size in millimetres."""
        return 25.4 / self.dpi

    @property
    def has_normals(self) -> bool:
        return self.normals is not None

    def window(self, r0: int, r1: int, c0: int, c1: int) -> "RGBNImage":
        """Rows ``r0:r1``, columns ``c0:c1`` of every field (views, not copies); ``attrs`` copied."""
        cut = {name: getattr(self, name)[r0:r1, c0:c1] for name in _OPTIONAL if getattr(self, name) is not None}
        return RGBNImage(albedo=self.albedo[r0:r1, c0:c1], mask=self.mask[r0:r1, c0:c1], dpi=self.dpi,
                         attrs=dict(self.attrs), **cut)


_OPTIONAL = ("normals", "confidence", "discontinuity", "height_mm")


def write_rgbn(group: h5py.Group, image: RGBNImage) -> None:
    """Write an RGBN image into an open HDF5 group (datasets compressed, chunked)."""
    opts = dict(compression="gzip", compression_opts=1, shuffle=True)
    group.attrs["dpi"] = image.dpi
    group.attrs["pixel_mm"] = image.pixel_mm
    group.attrs["normal_convention"] = "x right, y up, z towards viewer"
    for k, v in image.attrs.items():
        group.attrs[k] = v
    group.create_dataset("albedo", data=image.albedo, **opts)
    group.create_dataset("mask", data=image.mask, **opts)
    for name in _OPTIONAL:
        arr = getattr(image, name)
        if arr is not None:
            group.create_dataset(name, data=arr, **opts)


def read_rgbn(group: h5py.Group) -> RGBNImage:
    """Read an RGBN image written by :func:`write_rgbn`."""
    try:
        kw = {name: group[name][()] for name in _OPTIONAL if name in group}
        attrs = {k: v for k, v in group.attrs.items() if k not in ("dpi", "pixel_mm", "normal_convention",
                                                                    "schema", "schema_version", "created",
                                                                    "software_version", "provenance")}
        return RGBNImage(albedo=group["albedo"][()], mask=group["mask"][()], dpi=float(group.attrs["dpi"]),
                         attrs=attrs, **kw)
    except KeyError as exc:
        raise ArtifactError(f"RGBN data in {group.file.filename} lacks {exc}") from exc


def save_rgbn(store: Store, relpath: str, image: RGBNImage, *, provenance: Mapping | None = None) -> ArtifactRef:
    """Store an RGBN image as an immutable ``tessera.rgbn`` artifact."""
    return store.write(relpath, SCHEMA, SCHEMA_VERSION, lambda f: write_rgbn(f, image), provenance=provenance)


def load_rgbn(store: Store, ref: ArtifactRef | Mapping | str, *, check_limits: bool = False) -> RGBNImage:
    """Load (and digest-check, when given a pointer) a ``tessera.rgbn`` artifact.

    ``check_limits``: first check its declared dpi and sizes against the sane ranges of
    :mod:`common.limits` (as a stage does with its input), before a pixel is read.
    """
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        if check_limits:
            check_rgbn_file(f)
        return read_rgbn(f)
