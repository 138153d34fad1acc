"""Feature service: on ``rgbn.ready``, describe the face and publish ``features.ready`` (§5.4).

Reads the RGBN artifact, runs :func:`common.features.extract_features`, writes the
``tessera.features`` artifact at a content-keyed path (a re-delivered job finds it already there)
and returns the ``features.ready`` event.
"""

from __future__ import annotations

from common.features import extract_features, save_features
from common.features.table import SCHEMA_VERSION, WORK_PIXEL_MM
from common.messages import MessageError, new_message
from common.rgbn.image import load_rgbn
from common.store import ArtifactRef, content_key

SERVICE = "features"
VERSION = f"features-1.2/schema-{SCHEMA_VERSION}"  # bump when any descriptor changes


def output_path(fragment: str, face: str, rgbn_sha256: str, work_mm: float = WORK_PIXEL_MM) -> str:
    """Content-keyed path of the feature artifact of one face; another working grid than the
    default is part of the key (a changed setting makes a new table, not finds the old one)."""
    grid = () if work_mm == WORK_PIXEL_MM else (f"work_pixel_mm={work_mm:g}",)
    return f"fragments/{fragment}/features/{face}-{content_key(rgbn_sha256, SERVICE, VERSION, *grid)}.h5"


def work_pixel_mm(config) -> float:
    """``[services.features] work_pixel_mm`` (default 0.1 mm), checked."""
    value = (config or {}).get("work_pixel_mm", WORK_PIXEL_MM)
    try:
        value = float(value)
    except (TypeError, ValueError):
        value = float("nan")
    if not 0.01 <= value <= 1.0:
        raise ValueError(f"services.features.work_pixel_mm must be a number of mm in [0.01, 1], "
                         f"got {(config or {}).get('work_pixel_mm')!r}")
    return value


def handle(job: dict, ctx) -> list[dict]:
    """Describe the RGBN face named by an ``rgbn.ready`` job; return ``[features.ready]``."""
    if job.get("type") != "rgbn.ready":
        raise MessageError(f"features service handles rgbn.ready, got {job.get('type')!r}")
    ref = ArtifactRef.from_dict(job["artifact"])
    fragment, face = str(job["fragment"]), str(job.get("face", "front"))
    work_mm = work_pixel_mm(ctx.config)   # a bad setting fails the job even when an output exists
    relpath = output_path(fragment, face, ref.sha256, work_mm)
    if not ctx.store.exists(relpath):
        image = load_rgbn(ctx.store, ref, check_limits=True)  # absurd dpi or sizes: rejected before a pixel is read
        table = extract_features(image, face=face, fragment=fragment, work_pixel_mm=work_mm,
                                 progress=lambda f, t: ctx.progress(0.05 + 0.9 * f, t))
        ctx.log.info("fragment %s %s: %d patches, missing %s", fragment, face, table.n_patches,
                     table.missing_data or "nothing")
        out = save_features(ctx.store, relpath, table, provenance={
            "stage": SERVICE, "stage_version": VERSION, "fragment": fragment, "face": face,
            "inputs": [ref.to_dict()]})
    else:
        out = ctx.store.ref(relpath)
    return [new_message("features.ready", fragment=fragment, face=face, artifact=out)]
