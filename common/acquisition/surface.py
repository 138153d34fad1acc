"""A fragment's physical surface: what a (simulated) scanner or camera looks at.

The synthetic fresco produces these; the simulated flatbed scans them. Arrays follow the
RGBN conventions of :mod:`common.rgbn.image` (row 0 at the top).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FragmentSurface:
    """One face of a physical fragment, sampled on a regular grid.

    Attributes
    ----------
    albedo : (H, W, 3) float32
        Diffuse RGB reflectance in [0, 1].
    height_mm : (H, W) float32
        Relief height above the face's base plane in millimetres (the face looks up, +z).
    mask : (H, W) bool
        True on the fragment.
    dpi : float
        Sampling density of these arrays (pixel = 25.4 / dpi mm).
    thickness_mm : float
        Nominal plaster thickness (how high the back face lifts the front off the glass).
    back : FragmentSurface or None
        The other face, as seen after flipping the fragment over (mirror image), or None.
    """

    albedo: np.ndarray
    height_mm: np.ndarray
    mask: np.ndarray
    dpi: float
    thickness_mm: float = 10.0
    back: "FragmentSurface | None" = None

    def __post_init__(self):
        self.albedo = np.asarray(self.albedo, dtype=np.float32)
        self.height_mm = np.asarray(self.height_mm, dtype=np.float32)
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.albedo.ndim != 3 or self.albedo.shape[2] != 3:
            raise ValueError(f"albedo must be (H, W, 3), got {self.albedo.shape}")
        if self.height_mm.shape != self.albedo.shape[:2] or self.mask.shape != self.albedo.shape[:2]:
            raise ValueError("albedo, height_mm and mask must share (H, W)")
        if not self.dpi > 0:
            raise ValueError(f"dpi must be positive, got {self.dpi}")

    @property
    def pixel_mm(self) -> float:
        return 25.4 / self.dpi
