"""Renderer service: on ``rgbn.ready``, draw the face with the configured recipe and publish
``render.ready`` (§7.3).

Config ``[services.renderer]``: ``recipe`` = a shipped recipe name (``configs/recipes/<name>.toml``)
or a path to a TOML file; default ``"default"``. ``archive_tiles`` (default true): also cut the
tiles the archive pages show of the face and of its illustration
(:func:`common.web.relight.cut_archive_tiles`), so a fragment page opens at once instead of
cutting them on its first view. The output path is keyed by the RGBN digest, this stage's version
and the recipe text, so a re-delivered job finds its output and a new recipe makes a new
illustration; tiles are keyed by their artifact's content, so a re-delivered job finds them too.
"""

from __future__ import annotations

import hashlib

from common.messages import MessageError, new_message
from common.render.artifact import SCHEMA_VERSION, save_rendering
from common.limits import check_rgbn_file
from common.render.recipes import load_recipe
from common.render.tiles import render_h5
from common.rgbn.image import SCHEMA as RGBN_SCHEMA, SCHEMA_VERSION as RGBN_VERSION
from common.store import ArtifactRef, content_key
from common.web.relight import cut_archive_tiles

SERVICE = "renderer"
VERSION = f"render-2.1/schema-{SCHEMA_VERSION}"  # 2.0: readable defaults, colour relief, tiles; 2.1: colour-only faces keep their albedo under the lines (they were white)


def output_path(fragment: str, face: str, rgbn_sha256: str, recipe_text: str) -> str:
    """Content-keyed path of one illustration of one face."""
    recipe_digest = hashlib.sha256(recipe_text.encode()).hexdigest()
    return f"fragments/{fragment}/renders/{face}-{content_key(rgbn_sha256, SERVICE, VERSION, recipe_digest)}.h5"


def handle(job: dict, ctx) -> list[dict]:
    """Render the RGBN face named by an ``rgbn.ready`` job; return ``[render.ready]``."""
    if job.get("type") != "rgbn.ready":
        raise MessageError(f"renderer handles rgbn.ready, got {job.get('type')!r}")
    ref = ArtifactRef.from_dict(job["artifact"])
    fragment, face = str(job["fragment"]), str(job.get("face", "front"))
    recipe = load_recipe((ctx.config or {}).get("recipe", "default"))
    relpath = output_path(fragment, face, ref.sha256, recipe.source)
    if not ctx.store.exists(relpath):
        with ctx.store.open(ref, schema=RGBN_SCHEMA, version=RGBN_VERSION) as f:
            check_rgbn_file(f)  # absurd dpi or sizes: rejected before a pixel is read
            # a large face is read and drawn tile by tile (bounded memory)
            drawn, dpi = render_h5(f, recipe, progress=lambda p, t: ctx.progress(0.05 + 0.9 * p, t))
        if drawn.skipped:
            # a colour-only face (an imported picture) is normal, not a fault: said once, at INFO
            ctx.log.info("fragment %s %s has no normals: skipped %s", fragment, face, ", ".join(drawn.skipped))
        out = save_rendering(ctx.store, relpath, drawn, dpi=dpi, provenance={
            "stage": SERVICE, "stage_version": VERSION, "fragment": fragment, "face": face,
            "recipe": recipe.name, "inputs": [ref.to_dict()]})
    else:
        out = ctx.store.ref(relpath)
    if (ctx.config or {}).get("archive_tiles", True):
        for source in (ref.path, out.path):
            cut_archive_tiles(ctx.store, source)
        ctx.progress(1.0, "archive tiles cut")
    return [new_message("render.ready", fragment=fragment, face=face, artifact=out, recipe=recipe.name)]
