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

    # a dome capture: the lamps are near (radius in pixels, or the one that re-renders best)
    tessera ps item1/*.jpg --lights item1/dirs.lp --srgb --dome-radius auto -o item1.h5

Checked at the door (docs/handheld.md): every image decodes completely (truncated PNG/JPEG
refused), one bit depth, channel layout and size, no black, blank or overexposed image; images
matched to lights by position in shell order (1, 10, 11, 2, ...) are put in natural order with
a warning; an automatic mask keeping less than ``--min-mask-share`` asks for ``--mask``;
``--pictures`` / ``-o`` are checked before any work; a result with no solved pixel is never
written or announced. :func:`solve_capture` is also the code path of ``tessera import rti``.
With ``--store`` (or ``--submit``) the capture is checked, before the solve, against what was imported
before, as every import is: images already stored as another fragment, or for this face at another dpi,
are refused naming it (``--allow-duplicates`` / ``--replace``; ``common.imports.source_conflict``).

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
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger("tessera.ps")


def add_parser(subparsers) -> None:
    from services.cli.imports import add_duplicate_arguments

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
    solve.add_argument("--min-mask-share", type=float, default=None, metavar="F",
                       help="refuse an automatic mask keeping less than this share of the frame (default 0.05)")
    solve.add_argument("--dome-radius", metavar="PX|auto",
                       help="near lights on a dome of this radius in pixels (dome RTI captures), or 'auto': "
                            "the radius that re-renders the images best (default: distant lights)")
    solve.add_argument("--light-positions", type=float, metavar="PX_PER_UNIT",
                       help="the --lights file gives light positions (near lights) from the image centre, not "
                            "directions; PX_PER_UNIT pixels per unit of the file (1: pixels; dpi/25.4: mm)")
    solve.add_argument("--bit-depth", type=int, choices=(8, 16), help="declared bit depth: other files are refused")
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
    # with --store (and --submit): the capture is checked against what was imported before, as every import is
    add_duplicate_arguments(p)
    p.set_defaults(func=run)


def _capture_item(args):
    """The capture as an import item (:class:`common.imports.ImportItem`) for the check against the files
    imported before: the images are the fragment's own files; the rig's — light file, intensities, mask, sphere
    masks and sphere images — say nothing of which fragment it is (shared, as ``tessera import rti`` has them)."""
    from common.imports import ImportItem

    rig = [v for v in (args.lights, args.intensities, args.mask) if v]
    rig += [v for v in (args.chrome, args.diffuse) if v and Path(v).is_file()]   # a sphere given as a mask file
    rig += list(args.chrome_images or []) + list(args.diffuse_images or [])
    return ImportItem(name=Path(args.images[0]).parent.name or args.images[0], sources=[*args.images, *rig],
                      fragment=args.fragment, face=args.face, options={"dpi": float(args.dpi)}, shared=rig)


def _refuse_a_second_copy(item, store, args) -> None:
    """Refuse (ValueError) a capture whose images are already stored as another fragment, or for this face at
    another dpi: the check every import makes (:func:`common.imports.source_conflict`; ``--allow-duplicates`` /
    ``--replace``). Made before the solve, so a refused capture costs nothing."""
    from common.imports import ImportRefused, StoreSink, load_sources, source_conflict

    try:
        item.fill_digests()
    except OSError:
        return   # a file that cannot be read is refused at the door by the solve, which names it
    reason = source_conflict(item, load_sources(StoreSink(store)), allow_duplicates=args.allow_duplicates,
                             replace=args.replace)
    if reason:
        raise ImportRefused(f"{reason}; nothing written")


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


@dataclass
class Solved:
    """A solved capture: the RGBN image and what a writer needs to store and announce it."""

    rgbn: object
    provenance: dict
    digest: str
    method: str
    residual: np.ndarray
    warnings: list = field(default_factory=list)


def _check_outputs(output=None, pictures=None, write_lp=None) -> None:
    """Refuse unusable output paths before any work, so nothing is half-written."""
    if write_lp is not None and (Path(write_lp).is_dir() or not Path(write_lp).parent.is_dir()):
        raise ValueError(f"--write-lp {write_lp}: give a file name in an existing directory")
    if pictures is not None:
        pic = Path(pictures)
        if pic.exists() and not pic.is_dir():
            raise ValueError(f"--pictures {pictures} is a file, not a directory: give a directory for the PNGs")
        parent = next((q for q in [pic, *pic.parents] if q.exists()), Path("."))
        if not parent.is_dir() or not os.access(parent, os.W_OK):
            raise ValueError(f"--pictures {pictures}: {parent} is not a writable directory")
    if output is not None:
        out = Path(output)
        if out.is_dir():
            raise ValueError(f"-o {output} is a directory: give the name of the HDF5 file to write")
        if not out.parent.is_dir():
            raise ValueError(f"-o {output}: the directory {out.parent} does not exist")


def _position_order(paths: list[Path], what: str, warnings: list) -> list[Path]:
    """Images matched to lights by position: a shell-sorted list (1, 10, 11, 2, ...) is put in natural order."""
    from common.acquisition.lightfile import natural_order, shell_sorted

    if shell_sorted(paths):
        fixed = [paths[i] for i in natural_order(paths)]
        warnings.append(f"the {what} were listed in character order ({', '.join(p.name for p in paths[:4])}, ...), "
                        f"as a shell glob gives unpadded numbers; they are matched to the lights in natural order "
                        f"({', '.join(p.name for p in fixed[:4])}, ...)")
        return fixed
    return paths


def solve_capture(images, *, lights=None, intensities=None, chrome=None, chrome_images=None, diffuse=None,
                  diffuse_images=None, mask=None, method: str = "robust", srgb: bool = False, dpi: float = 96.0,
                  bit_depth: int | None = None, min_mask_share: float | None = None, dome_radius=None,
                  light_positions: float | None = None, discontinuities: bool = True, write_lp=None, progress=None) -> Solved:
    """Read, check and solve one flash/RTI capture: the one code path of ``tessera ps`` and ``tessera import rti``.

    Raises ValueError naming the file and the reason for anything refused (see docs/handheld.md,
    "Checked at the door"); an image with no solved pixel is refused, never returned.
    """
    from common.acquisition import handheld as hh
    from common.acquisition.lightfile import LightSet, read_intensities, read_lights, write_lp as save_lp
    from common.acquisition.photometric import ROBUST_MIN_IMAGES
    from common.acquisition.spheres import sphere_normals

    if bool(lights) == bool(chrome):
        raise ValueError("give exactly one of --lights FILE or --spheres/--chrome SPEC")
    warnings: list[str] = []
    paths = [Path(p) for p in images]
    if len(paths) < 3:
        raise ValueError(f"{len(paths)} image(s) given: photometric stereo needs at least 3 (30-100 for a robust solve)")
    if method == "robust" and len(paths) < ROBUST_MIN_IMAGES:
        raise ValueError(f"{len(paths)} images given: the robust solver needs at least {ROBUST_MIN_IMAGES} (it gives "
                         "confidence 0 to a pixel with 3 or fewer kept lights, full confidence from 3 + max(3, N/4)); "
                         "use --method least_squares")
    if light_positions is not None and (not lights or dome_radius not in (None, "")):
        raise ValueError("--light-positions needs --lights FILE and replaces --dome-radius")
    light_set = read_lights(lights, positions=light_positions) if lights else None
    if light_set is None or light_set.filenames is None:  # matched by position
        paths = _position_order(paths, "images", warnings)
    chrome_paths = [Path(p) for p in chrome_images or []]
    diffuse_paths = [Path(p) for p in diffuse_images or []]
    if chrome_paths:
        chrome_paths = _position_order(chrome_paths, "mirror-sphere images", warnings)
    if diffuse_paths:
        diffuse_paths = _position_order(diffuse_paths, "diffuse-sphere images", warnings)
    for extra, what in ((chrome_paths, "--chrome-images"), (diffuse_paths, "--diffuse-images")):
        if extra and len(extra) != len(paths):
            raise ValueError(f"{len(paths)} images but {len(extra)} {what}: one per flash")

    imgs, saturated = hh.read_images(paths, srgb=srgb, bit_depth=bit_depth)
    log.info("read %d images of %dx%d", len(paths), imgs.shape[2], imgs.shape[1])
    inputs = list(paths)
    exclude = np.zeros(imgs.shape[1:3], bool)
    if light_set is not None:
        light_set = light_set.subset(light_set.order_for(paths))
        inputs.append(Path(lights))
    else:
        chrome_imgs = imgs if not chrome_paths else hh.read_images(chrome_paths, srgb=srgb, bit_depth=bit_depth)[0]
        circle = _sphere_circle(chrome, chrome_imgs, "mirror")
        inputs += [Path(spec) for spec in (chrome, diffuse) if spec and Path(spec).is_file()]
        if not chrome_paths:
            exclude |= sphere_normals(exclude.shape, circle, shrink=1.05)[1]
        diffuse_imgs = diffuse_sat = dcircle = None
        if diffuse:
            if diffuse_paths:
                diffuse_imgs, diffuse_sat = hh.read_images(diffuse_paths, srgb=srgb, bit_depth=bit_depth)
            else:
                diffuse_imgs, diffuse_sat = imgs, saturated
            dcircle = _sphere_circle(diffuse, diffuse_imgs, "diffuse")
            if not diffuse_paths:
                exclude |= sphere_normals(exclude.shape, dcircle, shrink=1.05)[1]
        light_set = hh.sphere_lights(chrome_imgs, circle, diffuse_images=diffuse_imgs, diffuse_circle=dcircle,
                                     diffuse_saturated=diffuse_sat)
        inputs += chrome_paths + diffuse_paths
        log.info("mirror sphere at (%.1f, %.1f) r=%.1f px", *circle)
    if len(light_set) != len(imgs):
        raise ValueError(f"{len(imgs)} images but {len(light_set)} lights")
    if intensities:
        light_set = LightSet(light_set.directions, light_set.filenames, read_intensities(intensities),
                             light_set.positions)
        inputs.append(Path(intensities))

    if mask:
        obj = hh.read_mask(mask, imgs.shape[1:3])
        inputs.append(Path(mask))
        if not obj.any():
            raise ValueError(f"mask {mask} is empty: no object pixel")
    else:
        share = hh.MIN_MASK_SHARE if min_mask_share is None else min_mask_share
        obj = hh.object_mask(imgs, exclude=exclude, min_share=share)
        log.info("automatic mask: %.1f%% of the frame", 100 * obj.mean())

    radius = None
    if dome_radius not in (None, ""):
        if str(dome_radius).lower() == "auto":
            radius, table = hh.estimate_dome_radius(imgs, light_set, mask=obj, saturated=saturated)
            log.info("dome radius: %s (re-render residual %s)", "distant" if radius is None else f"{radius:.0f} px",
                     ", ".join(f"{'inf' if r is None else f'{r:.0f}'}: {v:.4f}" for r, v in table))
        else:
            try:
                radius = float(dome_radius)
            except ValueError:
                raise ValueError(f"--dome-radius {dome_radius!r}: expected pixels or 'auto'") from None

    rgbn = hh.handheld_rgbn(imgs, light_set, mask=obj, saturated=saturated, method=method, dpi=dpi,
                            discontinuities=discontinuities, dome_radius=radius, progress=progress)
    solved = rgbn.mask & (rgbn.confidence > 0)
    if not solved.any():
        raise ValueError(f"no pixel of the {'mask ' + str(mask) if mask else 'object'} could be solved "
                         f"({int(rgbn.mask.sum())} pixels, every one dark or unusable under all {len(imgs)} lights): "
                         "nothing written")
    residual = hh.rerender_residual(imgs, light_set, rgbn, dome_radius=radius)
    if write_lp:  # only once the capture has been accepted: a refused run leaves nothing behind
        save_lp(write_lp, [p.name for p in paths], light_set.directions)
    digest = _digest(inputs)
    provenance = {"device": "hand-held flash camera", "stage": "handheld", "version": hh.VERSION,
                  "method": method, "inputs_sha256": digest, "images": [p.name for p in paths],
                  "lights": light_set.directions.round(6).tolist(), "dpi_nominal": True,
                  "rerender_residual": residual.round(5).tolist()}
    if radius is not None:
        provenance["dome_radius_px"] = radius
    if light_set.positions is not None:
        provenance["light_positions_px"] = light_set.positions.round(3).tolist()
    log.info("solved %d pixels, mean confidence %.2f, re-render residual median %.3f (max %.3f)",
             int(solved.sum()), float(rgbn.confidence[rgbn.mask].mean()), float(np.median(residual)),
             float(residual.max()))
    return Solved(rgbn, provenance, digest, method, residual, warnings)


#: options of ``tessera ps`` that change the artifact, at their defaults (left out of the key there,
#: so artifacts stored before they were keyed keep their paths)
KEYED_DEFAULTS = {"srgb": False, "dpi": 96.0, "discontinuities": True, "chrome": None, "diffuse": None}


def rgbn_path(fragment: str, face: str, digest: str, method: str, dome_radius=None, light_positions=None,
              options: dict | None = None) -> str:
    """Content-keyed path of a hand-held capture's RGBN artifact.

    ``options``: settings of :data:`KEYED_DEFAULTS` (a run with other settings must not find the
    artifact of the first run in place and announce it as its own).
    """
    from common.acquisition.handheld import VERSION
    from common.store import content_key

    parts = (digest, method, "handheld", VERSION) + ((f"dome={dome_radius}",) if dome_radius not in (None, "") else ())
    parts += (f"positions={light_positions}",) if light_positions is not None else ()
    for name, default in KEYED_DEFAULTS.items():
        value = (options or {}).get(name, default)
        if value != default:
            parts += (f"{name}={value}",)
    return f"fragments/{fragment}/rgbn/{face}-{content_key(*parts)}.h5"


def _run(args) -> int:
    from common.acquisition import handheld as hh
    from common.messages import new_message, to_json
    from common.rgbn.image import SCHEMA, SCHEMA_VERSION, save_rgbn, write_rgbn
    from common.store import Store

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
    _check_outputs(args.output, args.pictures, args.write_lp)
    capture = None
    if args.store:
        capture = _capture_item(args)
        _refuse_a_second_copy(capture, Store(args.store), args)

    def progress(fraction, text):
        log.debug("%3.0f%% %s", 100 * fraction, text)

    done = solve_capture(args.images, lights=args.lights, intensities=args.intensities, chrome=args.chrome,
                         chrome_images=args.chrome_images, diffuse=args.diffuse, diffuse_images=args.diffuse_images,
                         mask=args.mask, method=args.method, srgb=args.srgb, dpi=args.dpi, bit_depth=args.bit_depth,
                         min_mask_share=args.min_mask_share, dome_radius=args.dome_radius,
                         light_positions=args.light_positions, discontinuities=not args.no_discontinuities,
                         write_lp=args.write_lp, progress=progress)
    for w in done.warnings:
        print(f"tessera ps: warning: {w}", file=sys.stderr)
    rgbn, provenance = done.rgbn, done.provenance
    if capture is not None and capture.digests:
        # what the check of the next import or ps reads from the artifact: its images, the rig's files, the dpi
        provenance = dict(provenance, **capture.source_provenance())

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
        # a sphere given as a mask file is in the digest; a circle or 'auto' is keyed by its text
        spec = lambda v: None if v is None or Path(v).is_file() else v  # noqa: E731
        options = {"srgb": bool(args.srgb), "dpi": float(args.dpi), "discontinuities": not args.no_discontinuities,
                   "chrome": spec(args.chrome), "diffuse": spec(args.diffuse)}
        relpath = rgbn_path(args.fragment, args.face, done.digest, args.method, args.dome_radius, args.light_positions,
                            options)
        ref = save_rgbn(store, relpath, rgbn, provenance=provenance)
        event = new_message("rgbn.ready", fragment=args.fragment, face=args.face, artifact=ref,
                            source="handheld", method=args.method)
        print(to_json(event, indent=2))
        if args.submit:
            from common.bus.client import BrokerRefused, BrokerUnavailable, submit

            try:
                seq = submit(event, config)
            except (BrokerUnavailable, BrokerRefused) as exc:
                print(f"tessera ps: the artifact is stored, but the event was not submitted: {exc}", file=sys.stderr)
                return 1
            print(f"submitted rgbn.ready as event {seq}")
    return 0
