"""``tessera render``: draw an RGBN image in any style or with a recipe (§7.3).

Examples::

    # an RGBN artifact (HDF5) in one style, 16-bit TIFF
    tessera render fragments/F0042/rgbn/front-3fa2c1.h5 --style exaggerated -o F0042.tif --bits 16

    # with a recipe (a shipped name or a TOML file)
    tessera render front.h5 --recipe relief -o relief.png

    # a normal map and an albedo photograph from another tool (DirectX normal map)
    tessera render --normals N.png --albedo A.png --convention directx --dpi 600 \\
        --style ridges_valleys -p threshold=0.5 -o ridges.png

    tessera render --list-styles      # every style and its parameters
"""

from __future__ import annotations

import argparse
import ast
import logging
import sys

log = logging.getLogger("tessera.render")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("render", help="draw an RGBN image: shading, lines, toon, exaggerated, ...",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", nargs="?", help="RGBN artifact (.h5); or use --normals/--albedo")
    src = p.add_argument_group("input from common files")
    src.add_argument("--normals", metavar="FILE", help="normal map: 8/16-bit PNG/TIFF, or float .npy/.tif")
    src.add_argument("--albedo", metavar="FILE", help="albedo/colour image on the same pixel grid")
    src.add_argument("--convention", choices=("auto", "opengl", "directx"), default="auto",
                     help="normal-map green axis: opengl = y up, directx = y down; auto (default) decides by "
                          "the curl of the two readings and logs the evidence")
    src.add_argument("--dpi", type=float, default=300.0, help="sampling density for file input (nominal if unknown)")
    src.add_argument("--linear-albedo", action="store_true", help="the albedo file is linear, not sRGB")
    how = p.add_argument_group("what to draw")
    how.add_argument("--style", help="one style (see --list-styles)")
    how.add_argument("--recipe", metavar="FILE|NAME",
                     help="a recipe TOML file or a shipped recipe name (default: default, colour plus relief)")
    how.add_argument("-p", "--param", action="append", default=[], metavar="NAME=VALUE",
                     help="style parameter for --style (repeatable), e.g. -p scales=6 -p light=[90,20]")
    how.add_argument("--list-styles", action="store_true", help="list the styles and their parameters, then exit")
    out = p.add_argument_group("output")
    out.add_argument("-o", "--output", metavar="OUT", help="output image: .png, .tif or .tiff")
    out.add_argument("--bits", type=int, choices=(8, 16), help="bits per channel (default: the recipe's, else 8)")
    out.add_argument("--alpha", action="store_true", help="write an alpha channel (coverage) as well")
    p.set_defaults(func=run)


def _parse_params(items: list[str]) -> dict:
    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--param {item!r}: expected NAME=VALUE")
        try:
            params[name] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            params[name] = {"true": True, "false": False}.get(value.lower(), value)
    return params


def _list_styles() -> int:
    from common.render.recipes import PARAM_DOCS, RECIPE_DIR, STYLES

    for style in STYLES.values():
        print(f"{style.name}: {style.summary}")
        for k, v in style.parameters().items():
            print(f"    {k} = {v!r}    # {PARAM_DOCS.get(k, '')}")
    print("shipped recipes: " + ", ".join(sorted(q.stem for q in RECIPE_DIR.glob('*.toml'))))
    return 0


def _load_input(args):
    from common.rgbn.io import load_rgbn_files

    if args.normals:
        if args.input:
            raise ValueError("give either an RGBN artifact or --normals, not both")
        return load_rgbn_files(args.normals, args.albedo, convention=args.convention, dpi=args.dpi,
                               srgb=False if args.linear_albedo else None)
    if not args.input:
        raise ValueError("no input: give an RGBN artifact (.h5) or --normals FILE [--albedo FILE]")
    import h5py

    from common.rgbn.image import SCHEMA, read_rgbn

    try:
        with h5py.File(args.input, "r", locking=False) as f:
            schema = f.attrs.get("schema")
            if schema is not None and schema != SCHEMA:
                raise ValueError(f"{args.input} is a {schema!r} artifact, not an RGBN image ({SCHEMA})")
            return read_rgbn(f)
    except OSError as exc:
        raise ValueError(f"{args.input} is not a readable HDF5 RGBN artifact ({exc})") from exc


def run(args) -> int:
    from common.render.recipes import load_recipe, render, style_recipe
    from common.rgbn.io import write_image

    if args.list_styles:
        return _list_styles()
    try:
        if args.style and args.recipe:
            raise ValueError("give at most one of --style or --recipe (neither: the default recipe)")
        if not args.output:
            raise ValueError("give the output image with -o OUT.png|OUT.tif")
        if args.param and not args.style:
            raise ValueError("--param goes with --style (a recipe carries its own parameters)")
        recipe = (style_recipe(args.style, **_parse_params(args.param)) if args.style
                  else load_recipe(args.recipe or "default"))
        image = _load_input(args)
        log.info("drawing %dx%d px (%.0f dpi) with %s", image.shape[1], image.shape[0], image.dpi, recipe.name)
        drawn = render(image, recipe, progress=lambda f, t: log.info("%3.0f%% %s", 100 * f, t))
        for layer, chosen in zip(recipe.layers, drawn.resolved):
            if chosen:
                log.info("%s chose %s", layer["style"], chosen)
        bits = args.bits or recipe.bits
        path = write_image(args.output, drawn.rgb, bits=bits, alpha=drawn.alpha if args.alpha else None)
    except (ValueError, FileNotFoundError) as exc:
        print(f"tessera render: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0
