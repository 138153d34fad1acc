"""The ``tessera.render`` artifact: one illustration of one face, on the RGBN image's pixel grid."""

from __future__ import annotations

from typing import Mapping

import numpy as np

from common.render.recipes import Rendering
from common.store import ArtifactError, ArtifactRef, Store

SCHEMA = "tessera.render"
SCHEMA_VERSION = 1


def to_integer(values: np.ndarray, bits: int) -> np.ndarray:
    """[0, 1] floats (or an 8/16-bit image drawn in tiles) as uint8 / uint16."""
    from common.rgbn.io import to_bits

    return to_bits(values, bits)


def save_rendering(store: Store, relpath: str, rendering: Rendering, *, dpi: float,
                   provenance: Mapping | None = None) -> ArtifactRef:
    """Store a rendering: datasets ``image`` (H, W, 3) and ``alpha`` (H, W) as uint8/uint16 (the
    recipe's ``bits``), attributes ``recipe`` (name), ``recipe_toml``, ``bits``, ``dpi``,
    ``skipped_styles``."""
    bits = rendering.recipe.bits

    def fill(f):
        opts = dict(compression="gzip", compression_opts=1, shuffle=True)
        f.create_dataset("image", data=to_integer(rendering.rgb, bits), **opts)
        f.create_dataset("alpha", data=to_integer(rendering.alpha, bits), **opts)
        f.attrs["recipe"] = rendering.recipe.name
        f.attrs["recipe_toml"] = rendering.recipe.source
        f.attrs["bits"] = bits
        f.attrs["dpi"] = float(dpi)
        f.attrs["pixel_mm"] = 25.4 / float(dpi)
        f.attrs["colour_encoding"] = "display (sRGB-encoded albedo, shading as drawn)"
        f.attrs["skipped_styles"] = ",".join(rendering.skipped)

    return store.write(relpath, SCHEMA, SCHEMA_VERSION, fill, provenance=provenance)


def load_rendering(store: Store, ref) -> tuple[np.ndarray, np.ndarray, dict]:
    """(image (H, W, 3) float in [0, 1], alpha (H, W), attributes) of a ``tessera.render`` artifact."""
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        try:
            bits = int(f.attrs["bits"])
            full = 255.0 if bits == 8 else 65535.0
            image = f["image"][()].astype(np.float32) / full
            alpha = f["alpha"][()].astype(np.float32) / full
        except KeyError as exc:
            raise ArtifactError(f"render artifact {ref} lacks {exc}") from exc
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return image, alpha, attrs
