"""``tessera ps``: hand-held flash photometric stereo (thesis §3.2) → RGBN artifact + ``rgbn.ready``.

Examples::

    # an RTI capture with its .lp light file, into the station's store, announced on the bus
    tessera ps shots/*.jpg --lights shots/capture.lp --srgb --store /srv/tessera \\
        --fragment F0042 --face front --submit

    # spheres photographed under the same flashes (psm-seitz layout); pictures only
    tessera ps cat/cat.*.png --mask cat/cat.mask.png \\
        --chrome chrome/chrome.mask.png --chrome-images chrome/chrome.*.png \\
        --diffuse gray/gray.mask.png --diffuse-images gray/gray.*.png \\
        -o cat.h5 --pictures cat-pictures/

    # mirror and diffuse spheres in the frame, circles in pixels (column, row, radius)
    tessera ps shots/*.tif --spheres 1710,220,95 1710,520,95 --pictures out/
    tessera ps shots/*.tif --spheres auto auto --pictures out/      # found automatically

``--spheres MIRROR [DIFFUSE]`` is short for ``--chrome MIRROR --diffuse DIFFUSE`` (put the
images first). A sphere is given as ``cx,cy,r`` (pixels: column, row, radius), as a mask
image, or as ``auto``: circles of the median image, told apart by their response to the moving
flash (a small moving spot on the mirror, Lambertian shading on the diffuse sphere). Without
``--chrome-images`` the mirror sphere is looked for in the capture images themselves and kept
out of the automatic object mask (likewise the diffuse sphere).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
from pathlib import Path

import numpy as np

log = logging.getLogger("tessera.ps")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("ps", help="hand-held flash photometric stereo → RGBN image",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("images", nargs="+", help="flash images of one view (8/16-bit PNG, TIFF, JPEG)")
    lights = p.add_argument_group("lights (one of --lights, --spheres or --chrome)")
    lights.add_argument("--lights", metavar="FILE", help=".lp file (filename x y z) or plain x y z directions")
    lights.add_argument("--intensities", metavar="FILE", help="per-image light intensity (1 or r g b per line)")
    lights.add_argument("--spheres", nargs="+", metavar="SPEC",
                        help="spheres in the frame: MIRROR [DIFFUSE] (same as --chrome MIRROR --diffuse DIFFUSE)")
    lights.add_argument("--chrome", metavar="SPEC", help="mirror sphere: cx,cy,r | mask image | auto")
    lights.add_argument("--chrome-images", nargs="+", metavar="IMG", help="mirror-sphere images (same flashes)")
    lights.add_argument("--diffuse", metavar="SPEC", help="diffuse sphere (intensities): cx,cy,r | mask image | auto")
    lights.add_argument("--diffuse-images", nargs="+", metavar="IMG", help="diffuse-sphere images (same flashes)")
    lights.add_argument("--write-lp", metavar="FILE", help="save the lights used as an .lp file")
    solve = p.add_argument_group("solve")
    solve.add_argument("--mask", metavar="FILE", help="object mask image (default: found automatically)")
    solve.add_argument("--method", choices=("robust", "least_squares"), default="robust")
    solve.add_argument("--srgb", action="store_true", help="images are sRGB-encoded (camera JPEGs): linearise")
    solve.add_argument("--dpi", type=float, default=96.0, help="sampling density of the view (nominal if unknown)")
    solve.add_argument("--no-discontinuities", action="store_true", help="skip the depth-discontinuity map")
    out = p.add_argument_group("output")
    out.add_argument("--store", metavar="DIR", help="storage root: write fragments/<id>/rgbn/<face>-<key>.h5 "
                     "(default with --submit: the config's [storage] root)")
    out.add_argument("--fragment", metavar="ID", help="fragment id (with --store)")
    out.add_argument("--face", choices=("front", "back"), default="front")
    out.add_argument("--submit", action="store_true", help="submit the rgbn.ready event to the broker")
    out.add_argument("--config", metavar="FILE", help="station config (broker address for --submit)")
    out.add_argument("-o", "--output", metavar="OUT.h5", help="also write the RGBN image to this HDF5 file")
    out.add_argument("--pictures", metavar="DIR", help="write normals/albedo/confidence/discontinuity PNGs")
    p.set_defaults(func=run)


def _sphere_circle(spec: str, images: np.ndarray, kind: str) -> np.ndarray:
    """Circle of the ``kind`` ('mirror' | 'diffuse') sphere from ``cx,cy,r``, a mask, or 'auto'."""
    from common.acquisition.handheld import read_mask
    from common.acquisition.spheres import find_calibration_spheres, find_sphere

    if spec == "auto":
        mirror, diffuse = find_calibration_spheres(images)
        if kind == "mirror":
            return mirror
        if diffuse is None:
            raise ValueError("no diffuse sphere found in the images; give its circle or a mask")
        return diffuse
    parts = spec.split(",")
    if len(parts) == 3:
        try:
            return np.array([float(v) for v in parts])
        except ValueError:
            pass
    if Path(spec).is_file():
        return find_sphere(read_mask(spec, images.shape[1:3]))
    raise ValueError(f"{kind} sphere {spec!r}: expected cx,cy,r in pixels, a mask image, or 'auto'")


def _digest(paths) -> str:
    h = hashlib.sha256()
    for p in paths:
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def run(args) -> int:
    try:
        return _run(args)
    except ValueError as exc:
        print(f"tessera ps: {exc}", file=sys.stderr)
        return 2


def _run(args) -> int:
    from common.acquisition import handheld as hh
    from common.acquisition.lightfile import LightSet, read_intensities, read_lights, write_lp
    from common.acquisition.spheres import sphere_normals
    from common.messages import new_message
    from common.rgbn.image import SCHEMA, SCHEMA_VERSION, save_rgbn, write_rgbn
    from common.store import Store, content_key

    if args.spheres:
        if args.chrome or args.diffuse or len(args.spheres) > 2:
            raise ValueError("--spheres takes MIRROR [DIFFUSE] and replaces --chrome/--diffuse")
        args.chrome = args.spheres[0]
        args.diffuse = args.spheres[1] if len(args.spheres) > 1 else None
    if bool(args.lights) == bool(args.chrome):
        raise ValueError("give exactly one of --lights FILE or --spheres/--chrome SPEC")
    config = None
    if args.submit:
        from common.config import load_config

        config = load_config(args.config)
        args.store = args.store or config["storage"]["root"]
    if args.store and not args.fragment:
        raise ValueError("--store and --submit need --fragment ID")
    if not (args.store or args.output or args.pictures):
        raise ValueError("nothing to write: give --store, -o OUT.h5 or --pictures DIR")

    paths = [Path(p) for p in args.images]
    images, saturated = hh.read_images(paths, srgb=args.srgb)
    log.info("read %d images of %dx%d", len(paths), images.shape[2], images.shape[1])
    inputs = list(paths)
    exclude = np.zeros(images.shape[1:3], bool)

    if args.lights:
        lights = read_lights(args.lights)
        lights = lights.subset(lights.order_for(paths))
        inputs.append(Path(args.lights))
    else:
        chrome_imgs = images if not args.chrome_images else hh.read_images(args.chrome_images, srgb=args.srgb)[0]
        circle = _sphere_circle(args.chrome, chrome_imgs, "mirror")
        if not args.chrome_images:
            exclude |= sphere_normals(exclude.shape, circle, shrink=1.05)[1]
        diffuse_imgs = diffuse_sat = dcircle = None
        if args.diffuse:
            if args.diffuse_images:
                diffuse_imgs, diffuse_sat = hh.read_images(args.diffuse_images, srgb=args.srgb)
            else:
                diffuse_imgs, diffuse_sat = images, saturated
            dcircle = _sphere_circle(args.diffuse, diffuse_imgs, "diffuse")
            if not args.diffuse_images:
                exclude |= sphere_normals(exclude.shape, dcircle, shrink=1.05)[1]
        lights = hh.sphere_lights(chrome_imgs, circle, diffuse_images=diffuse_imgs, diffuse_circle=dcircle,
                                  diffuse_saturated=diffuse_sat)
        inputs += [Path(p) for p in (args.chrome_images or []) + (args.diffuse_images or [])]
        log.info("mirror sphere at (%.1f, %.1f) r=%.1f px", *circle)
    if len(lights) != len(images):
        raise ValueError(f"{len(images)} images but {len(lights)} lights")
    if args.intensities:
        lights = LightSet(lights.directions, lights.filenames, read_intensities(args.intensities))
        inputs.append(Path(args.intensities))
    if args.write_lp:
        write_lp(args.write_lp, [p.name for p in paths], lights.directions)

    if args.mask:
        mask = hh.read_mask(args.mask, images.shape[1:3])
        inputs.append(Path(args.mask))
    else:
        mask = hh.object_mask(images, exclude=exclude)

    def progress(fraction, text):
        log.debug("%3.0f%% %s", 100 * fraction, text)

    rgbn = hh.handheld_rgbn(images, lights, mask=mask, saturated=saturated, method=args.method, dpi=args.dpi,
                            discontinuities=not args.no_discontinuities, progress=progress)
    digest = _digest(inputs)
    provenance = {"device": "hand-held flash camera", "stage": "handheld", "version": hh.VERSION,
                  "method": args.method, "inputs_sha256": digest, "images": [p.name for p in paths],
                  "lights": lights.directions.round(6).tolist(), "dpi_nominal": True}
    conf = float(rgbn.confidence[rgbn.mask].mean()) if rgbn.mask.any() else 0.0
    log.info("solved %d pixels, mean confidence %.2f", int(rgbn.mask.sum()), conf)

    if args.output:
        out = Path(args.output)
        Store(out.parent or ".").write(out.name, SCHEMA, SCHEMA_VERSION, lambda f: write_rgbn(f, rgbn),
                                       provenance=provenance, overwrite=True)
        print(f"wrote {out}")
    if args.pictures:
        for p in hh.write_pictures(rgbn, args.pictures):
            print(f"wrote {p}")
    if args.store:
        store = Store(args.store)
        key = content_key(digest, args.method, "handheld", hh.VERSION)
        relpath = f"fragments/{args.fragment}/rgbn/{args.face}-{key}.h5"
        ref = save_rgbn(store, relpath, rgbn, provenance=provenance)
        event = new_message("rgbn.ready", fragment=args.fragment, face=args.face, artifact=ref,
                            source="handheld", method=args.method)
        print(json.dumps(event, indent=2))
        if args.submit:
            from common.bus.client import BrokerRefused, BrokerUnavailable, submit

            try:
                seq = submit(event, config)
            except (BrokerUnavailable, BrokerRefused) as exc:
                print(f"tessera ps: the artifact is stored, but the event was not submitted: {exc}", file=sys.stderr)
                return 1
            print(f"submitted rgbn.ready as event {seq}")
    return 0
