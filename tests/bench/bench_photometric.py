"""Benchmark of hand-held flash photometric stereo (thesis §3.2, issue 4).

Run ``python tests/bench/bench_photometric.py [--docs]``. Prints:

* speed: least squares and robust solver on 96 images of 640×480 (0.3 Mpx), grey and RGB
  (targets: ≤ 1 s and ≤ 10 s);
* DiLiGenT ball: mean angular error of both solvers inside the mask (published least-squares
  baseline 4.10°; target for the robust solver ≤ 2.5°), and the distance to the published
  baseline normals;
* psm-seitz: light directions from the chrome sphere vs the source's ``lights.txt``, and vs an
  independent estimate from the diffuse (grey) sphere;
* reading: the 96 16-bit DiLiGenT ball PNGs decoded in parallel threads (target ≤ 1.5 s wall on
  2 cores, peak memory ≤ 2× the decoded stack), measured in a fresh process;
* masks: the automatic mask (light modulation) on the frame-filling RealRTI captures (share of
  the frame), on psm-seitz cat/owl and the DiLiGenT ball (IoU with the given masks), with the
  per-image re-render residuals of the robust solve;
* near lights: RealRTI item1/item8 (domes) solved with distant lights and with the dome radius
  found by ``estimate_dome_radius``: re-render residual and the tilt of the normals across the frame;
* with ``--docs``: writes the cat/owl normal and albedo pictures, the mask and near-light
  pictures to ``docs/handheld/``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from common.acquisition.handheld import handheld_rgbn, read_images, read_mask  # noqa: E402
from common.acquisition.lightfile import read_lights  # noqa: E402
from common.acquisition.photometric import least_squares_normals, robust_normals  # noqa: E402
from common.acquisition.spheres import find_sphere, mirror_sphere_directions, sphere_normals  # noqa: E402
from common.acquisition.spheres import diffuse_sphere_intensities  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def _angles(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


def _lights(n, seed=0):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(25, 85, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def bench_speed():
    h, w, n = 480, 640, 96
    lights = _lights(n)
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(h, w, 3)).astype(np.float32) * [0.4, 0.4, 0] + [0, 0, 1]
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    shade = np.clip(np.einsum("nk,hwk->nhw", lights.astype(np.float32), normals), 0, None)
    grey = (0.6 * shade).astype(np.float32)
    rgb = grey[..., None] * np.array([1.0, 0.8, 0.6], np.float32)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"speed: {n} images of {w}x{h} ({w * h / 1e6:.2f} Mpx); load average {load:.1f} on {os.cpu_count()} CPUs")
    for name, images in (("grey", grey), ("RGB", rgb)):
        for solver, target in ((least_squares_normals, 1.0), (robust_normals, 10.0)):
            t, c = time.perf_counter(), time.process_time()
            out = solver(images, lights)
            dt, dc = time.perf_counter() - t, time.process_time() - c
            err = _angles(out.normals, normals).mean()
            print(f"  {solver.__name__:22s} {name:4s} {dt:6.2f} s wall, {dc:6.2f} s CPU  (target <= {target:.0f} s)  "
                  f"mean error {err:.3f} deg")
        del images


_DECODE_CHILD = """
import os, resource, sys, time
sys.path.insert(0, {root!r})
import numpy as np
from common.acquisition.handheld import read_images
paths = {paths!r}
import psutil
read_images(paths[:2], threads=1)  # warm the decoders up
base = psutil.Process().memory_info().rss / 1024  # now, in KiB like ru_maxrss
t, c = time.perf_counter(), time.process_time()
images, saturated = read_images(paths, threads={threads})
dt, dc = time.perf_counter() - t, time.process_time() - c
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(dt, dc, (peak - base) * 1024, images.nbytes + saturated.nbytes, images.shape)
"""


def bench_decode():
    """Decode the 96 16-bit DiLiGenT PNGs in a fresh process: wall, CPU, peak memory vs the stack."""
    root = DATA / "diligent-ball"
    if not root.is_dir():
        print(f"decode: data not present at {root}, skipped")
        return
    import tempfile

    ball = [str(root / n) for n in (root / "filenames.txt").read_text().split()]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"decode: load average {load:.1f} on {os.cpu_count()} CPUs")
    with tempfile.TemporaryDirectory() as tmp:
        # full DiLiGenT frames are 612x512: 96 16-bit RGB PNGs of a smooth shaded scene, as the camera gives
        rng = np.random.default_rng(0)
        base = cv2.GaussianBlur(rng.uniform(0.2, 0.8, (512, 612, 3)).astype(np.float32), (0, 0), 4)
        full = []
        for i, l in enumerate(_lights(96)):
            img = base * (0.3 + 0.7 * l[2]) + rng.normal(0, 0.004, base.shape).astype(np.float32)
            full.append(str(Path(tmp) / f"{i:03d}.png"))
            cv2.imwrite(full[-1], np.clip(img * 65535, 0, 65535).astype(np.uint16))
        for label, paths in (("DiLiGenT ball (cropped)", ball), ("96 x 612x512 16-bit RGB", full)):
            _decode_runs(label, paths)


def _decode_runs(label, paths):
    for threads in (1, os.cpu_count() or 1):
        code = _DECODE_CHILD.format(root=str(ROOT), paths=paths, threads=threads)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
        dt, dc, grown, stack = float(out[0]), float(out[1]), float(out[2]), float(out[3])
        shape = " ".join(out[4:])
        print(f"  {label}, read_images threads={threads}: {dt:.2f} s wall, {dc:.2f} s CPU (target <= 1.5 s wall); "
              f"stack {shape} = {stack / 2**20:.0f} MiB, peak memory grew {grown / 2**20:.0f} MiB = "
              f"{grown / stack:.2f}x the stack (target <= 2)")


def _iou(a, b):
    return float((a & b).sum() / max((a | b).sum(), 1))


def _residual_text(res):
    return f"re-render residual per image median {np.median(res):.3f}, p90 {np.percentile(res, 90):.3f}, max {res.max():.3f}"


def bench_masks(docs: bool = False):
    """The automatic mask on real captures, and the per-image re-render residuals of the robust solve."""
    from common.acquisition.handheld import object_mask, rerender_residual
    from common.acquisition.lightfile import LightSet

    rti = DATA / "realrti-dev"
    if not rti.is_dir():
        print(f"masks: data not present at {DATA}, skipped")
        return
    print("automatic mask (light modulation), no --mask:")
    pics = []
    for item in ("item1", "item5", "item8"):
        paths = sorted((rti / item).glob("*.jpg"))
        images, sat = read_images(paths, srgb=True)
        lights = read_lights(rti / item / "dirs.lp")
        lights = lights.subset(lights.order_for(paths))
        info = {}
        mask = object_mask(images, info=info)
        rgbn = handheld_rgbn(images, lights, mask=mask, saturated=sat, discontinuities=False)
        res = rerender_residual(images, lights, rgbn)
        print(f"  RealRTI {item}: mask covers {100 * mask.mean():.1f}% of the frame (frame-filling; background found: "
              f"{info['background']}); {_residual_text(res)}")
    for obj in ("cat", "owl"):
        root = DATA / "psm-seitz" / obj
        images, sat = read_images(sorted(root.glob(f"{obj}.[0-9]*.png")))
        truth = read_mask(root / f"{obj}.mask.png")
        mask = object_mask(images)
        old = _otsu_max_mask(images)
        lights = read_lights(DATA / "psm-seitz" / "lights.txt")
        rgbn = handheld_rgbn(images, lights, mask=mask, saturated=sat, discontinuities=False)
        res = rerender_residual(images, lights, rgbn)
        print(f"  psm-seitz {obj}: IoU with {obj}.mask.png {_iou(mask, truth):.3f} (Otsu on the max image: "
              f"{_iou(old, truth):.3f}); {_residual_text(res)}")
        pics.append((obj, images, mask, truth))
    root = DATA / "diligent-ball"
    names = (root / "filenames.txt").read_text().split()
    images, sat = read_images([root / n for n in names])
    lights = read_lights(root / "light_directions.txt", root / "light_intensities.txt")
    truth = read_mask(root / "mask.png")
    mask = object_mask(images)
    rgbn = handheld_rgbn(images, lights, mask=mask, saturated=sat, discontinuities=False)
    res = rerender_residual(images, lights, rgbn)
    print(f"  DiLiGenT ball: IoU with mask.png {_iou(mask, truth):.3f} (Otsu on the max image: "
          f"{_iou(_otsu_max_mask(images), truth):.3f}); {_residual_text(res)}")
    if docs:
        tiles = []
        for obj, images, mask, truth in pics:
            grey = np.sqrt(images.max(axis=0).mean(-1))
            grey = grey / max(grey.max(), 1e-6)
            tile = np.dstack([grey] * 3)
            edge = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
            edge_t = cv2.morphologyEx(truth.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
            tile[edge_t] = (0.0, 0.4, 1.0)
            tile[edge] = (1.0, 0.3, 0.0)
            tiles.append(tile)
        path = ROOT / "docs" / "handheld" / "auto_mask.png"
        cv2.imwrite(str(path), (np.clip(np.hstack(tiles), 0, 1) * 255).astype(np.uint8)[..., ::-1])
        print(f"  wrote {path.relative_to(ROOT)} (orange: automatic mask outline, blue: the given mask)")


def _otsu_max_mask(images):
    """The former automatic mask (Otsu on the max image), for comparison."""
    grey = np.sqrt(np.clip(images.max(axis=0).max(axis=-1), 0, None))
    u8 = np.clip(grey / max(float(grey.max()), 1e-12) * 255, 0, 255).astype(np.uint8)
    _, fg = cv2.threshold(u8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    obj = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    flood = np.pad(1 - obj, 1, constant_values=1)
    cv2.floodFill(flood, None, (0, 0), 2)
    return flood[1:-1, 1:-1] != 2


def bench_near_light(docs: bool = False):
    """Dome captures: distant vs near lights (radius from estimate_dome_radius)."""
    from common.acquisition.handheld import estimate_dome_radius, normal_tilt_gradient, rerender_residual
    from common.rgbn.io import encode_normal_map

    rti = DATA / "realrti-dev"
    if not rti.is_dir():
        print(f"near lights: data not present at {rti}, skipped")
        return
    print("near lights (dome captures, whole frame, least squares):")
    for item in ("item1", "item8"):
        paths = sorted((rti / item).glob("*.jpg"))
        images, sat = read_images(paths, srgb=True)
        lights = read_lights(rti / item / "dirs.lp")
        lights = lights.subset(lights.order_for(paths))
        h, w = images.shape[1:3]
        mask = np.ones((h, w), bool)
        t, c = time.perf_counter(), time.process_time()
        radius, table = estimate_dome_radius(images, lights, mask=mask, saturated=sat)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        print(f"  {item}: estimate_dome_radius {dt:.1f} s wall, {dc:.1f} s CPU: "
              + ", ".join(f"{'distant' if r is None else f'{r / max(h, w):.1f}w'} {v:.4f}" for r, v in table))
        rows = []
        runs = [("distant lights", None)]
        if radius is None:
            print("    near lights: no radius re-renders better than distant lights (auto keeps distant)")
        else:
            runs.append((f"auto: dome radius {radius / max(h, w):.1f}w", radius))
        runs.append(("dome radius 5.0w", 5.0 * max(h, w)))
        for label, r in runs:
            rgbn = handheld_rgbn(images, lights, mask=mask, saturated=sat, method="least_squares",
                                 discontinuities=False, dome_radius=r)
            res = rerender_residual(images, lights, rgbn, dome_radius=r)
            gx, gy = normal_tilt_gradient(rgbn)
            print(f"    {label:26s}: residual mean {res.mean():.4f}, median {np.median(res):.4f}; "
                  f"tilt across the frame {gx:+.1f} deg/width (x), {gy:+.1f} deg/height (y)")
            rows.append(encode_normal_map(rgbn.normals, rgbn.mask))
        if docs:
            # exaggerate the slow tilt: normals' x, y ×4 around mid-grey
            gap = np.ones((h, 6, 3))
            pic = np.hstack([x for r in rows for x in (np.clip(0.5 + 4 * (r - 0.5), 0, 1), gap)][:-1])
            path = ROOT / "docs" / "handheld" / f"near_light_{item}.png"
            cv2.imwrite(str(path), (pic * 255).astype(np.uint8)[..., ::-1])
            print(f"    wrote {path.relative_to(ROOT)} (normals ×4 in x/y: " + " | ".join(lb for lb, _ in runs) + ")")


def bench_diligent(docs: bool = False):
    root = DATA / "diligent-ball"
    if not root.is_dir():
        print(f"diligent-ball: data not present at {root}, skipped")
        return
    names = (root / "filenames.txt").read_text().split()
    images, saturated = read_images([root / n for n in names])
    lights = read_lights(root / "light_directions.txt", root / "light_intensities.txt")
    images /= lights.intensities[:, None, None, :].astype(np.float32)
    mask = read_mask(root / "mask.png")
    truth = np.load(root / "normal_gt.npy")
    baseline = np.load(root / "baseline_l2_normal.npy")
    print(f"DiLiGenT ball: {len(names)} images, {int(mask.sum())} pixels in the mask")
    print(f"  published least-squares baseline normals: {_angles(baseline, truth)[mask].mean():.2f} deg "
          f"(paper: 4.10)")
    runs = [("least squares", least_squares_normals, {}),
            ("least squares, saturated dropped", least_squares_normals, {"valid": ~saturated}),
            ("robust", robust_normals, {"valid": ~saturated})]
    maps = []
    for label, solver, kw in runs:
        t = time.perf_counter()
        out = solver(images, lights.directions, mask=mask, **kw)
        dt = time.perf_counter() - t
        err = _angles(out.normals, truth)[mask]
        print(f"  {label:34s} mean {err.mean():.2f} deg, median {np.median(err):.2f}, "
              f"vs baseline normals {_angles(out.normals, baseline)[mask].mean():.2f} deg, {dt:.2f} s")
        maps.append(np.where(mask, _angles(out.normals, truth), 0))
    if docs:
        # angular error, 0 (black) .. 10 degrees (white), least squares | robust
        pic = np.hstack([maps[0], np.zeros((mask.shape[0], 4)), maps[2]]) / 10.0
        pic = cv2.applyColorMap((np.clip(pic, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
        path = ROOT / "docs" / "handheld" / "diligent_ball_error.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), cv2.resize(pic, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST))
        print(f"  wrote {path.relative_to(ROOT)}")


def _seitz_stack(root, obj):
    return read_images([root / obj / f"{obj}.{i:02d}.png" for i in range(12)])


def bench_seitz(docs: bool):
    root = DATA / "psm-seitz"
    if not root.is_dir():
        print(f"psm-seitz: data not present at {root}, skipped")
        return
    chrome, _ = _seitz_stack(root, "chrome")
    circle = find_sphere(read_mask(root / "chrome" / "chrome.mask.png"))
    found = mirror_sphere_directions(chrome, circle)
    ref = read_lights(root / "lights.txt").directions
    ang = _angles(found, ref)
    print(f"psm-seitz: chrome sphere circle ({circle[0]:.1f}, {circle[1]:.1f}) r={circle[2]:.1f} px")
    print("  light | chrome-sphere direction      | lights.txt direction         | angle")
    for i, (a, b, d) in enumerate(zip(found, ref, ang)):
        print(f"  {i:5d} | {a[0]:+.3f} {a[1]:+.3f} {a[2]:+.3f}         | {b[0]:+.3f} {b[1]:+.3f} {b[2]:+.3f}"
              f"         | {d:.2f} deg")
    print(f"  chrome vs lights.txt: mean {ang.mean():.2f} deg, max {ang.max():.2f} deg")
    from common.acquisition.spheres import find_calibration_spheres

    auto, _ = find_calibration_spheres(chrome)
    ang_auto = _angles(mirror_sphere_directions(chrome, auto), ref)
    print(f"  circle found without the mask ({auto[0]:.1f}, {auto[1]:.1f}) r={auto[2]:.1f} px: "
          f"vs lights.txt mean {ang_auto.mean():.2f} deg, max {ang_auto.max():.2f} deg; "
          f"vs the mask circle's lights mean {_angles(mirror_sphere_directions(chrome, auto), found).mean():.2f} deg")
    # an independent check: fit each light to the grey (diffuse) sphere's shading
    gray, gsat = _seitz_stack(root, "gray")
    gcircle = find_sphere(read_mask(root / "gray" / "gray.mask.png"))
    normals, inside = sphere_normals(gray.shape[1:3], gcircle, shrink=0.9)
    nv = normals[inside]
    est = []
    for img, sat in zip(gray.mean(-1), gsat):
        vals, ok = img[inside], ~sat[inside]
        use = ok & (vals > 0.05 * vals.max())
        for _ in range(5):
            l, *_ = np.linalg.lstsq(nv[use], vals[use], rcond=None)
            use = ok & (nv @ l > 0.1 * np.linalg.norm(l))
        est.append(l / np.linalg.norm(l))
    est = np.asarray(est)
    print(f"  grey-sphere shading fit vs chrome: mean {_angles(est, found).mean():.2f} deg; "
          f"vs lights.txt: mean {_angles(est, ref).mean():.2f} deg")
    e = diffuse_sphere_intensities(gray, gcircle, found, valid=~gsat)
    print(f"  relative intensities from the grey sphere: {e.mean(1).min():.3f} .. {e.mean(1).max():.3f}")
    for obj in ("cat", "owl"):
        images, sat = _seitz_stack(root, obj)
        mask = read_mask(root / obj / f"{obj}.mask.png")
        from common.acquisition.lightfile import LightSet

        t = time.perf_counter()
        rgbn = handheld_rgbn(images, LightSet(found, intensities=e), mask=mask, saturated=sat)
        dt = time.perf_counter() - t
        print(f"  {obj}: {int(mask.sum())} pixels, mean confidence {rgbn.confidence[mask].mean():.2f}, "
              f"{rgbn.attrs['mean_inliers']:.1f} of 12 lights used per pixel, {dt:.2f} s")
        if docs:
            _write_docs_picture(obj, rgbn)


def _write_docs_picture(obj, rgbn):
    from common.rgbn.io import encode_normal_map, linear_to_srgb

    out = ROOT / "docs" / "handheld"
    out.mkdir(parents=True, exist_ok=True)
    rows, cols = np.nonzero(rgbn.mask)
    r0, r1 = max(rows.min() - 4, 0), rows.max() + 5
    c0, c1 = max(cols.min() - 4, 0), cols.max() + 5
    normals = encode_normal_map(rgbn.normals, rgbn.mask)[r0:r1, c0:c1]
    albedo = linear_to_srgb(rgbn.albedo / max(np.percentile(rgbn.albedo[rgbn.mask], 99), 1e-6))
    albedo = np.where(rgbn.mask[..., None], albedo, 0)[r0:r1, c0:c1]
    pic = np.hstack([normals, albedo])
    path = out / f"{obj}.png"
    cv2.imwrite(str(path), (np.clip(pic, 0, 1) * 255).astype(np.uint8)[..., ::-1])
    print(f"  wrote {path.relative_to(ROOT)} ({path.stat().st_size // 1024} KB)")


def docs_discontinuity():
    """Picture: a simulated flash capture of a relief and its directional discontinuity map."""
    from common.acquisition.discontinuity import depth_discontinuities
    from common.acquisition.handheld import discontinuity_picture, simulate_flash_capture
    from common.acquisition.surface import FragmentSurface
    from common.rgbn.io import linear_to_srgb

    size, dpi = 160, 254.0
    px = 25.4 / dpi
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    height = np.zeros((size, size))
    height[(cols - 55) ** 2 + (rows - 60) ** 2 < 30 ** 2] = 8 * px          # raised disc
    height[95:140, 90:145] = 5 * px                                         # a step block
    height[20:40, 100:150] = np.linspace(0, 6 * px, 50)[None, :]            # a ramp ending in a cliff
    rng = np.random.default_rng(1)
    albedo = cv2.GaussianBlur(rng.uniform(0.4, 0.9, (size, size, 3)).astype(np.float32), (0, 0), 3)
    surface = FragmentSurface(albedo, height, np.ones((size, size), bool), dpi)
    az = np.radians(np.arange(8) * 45 + 20)
    el = np.radians(40)
    lights = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(8, np.sin(el))])
    images = simulate_flash_capture(surface, lights, ambient=0.05)
    disc = depth_discontinuities(images, lights)
    pic = np.hstack([linear_to_srgb(images[0]), linear_to_srgb(images[3]), np.ones((size, 4, 3)),
                     discontinuity_picture(disc)])
    path = ROOT / "docs" / "handheld" / "discontinuity.png"
    cv2.imwrite(str(path), (np.clip(pic, 0, 1) * 255).astype(np.uint8)[..., ::-1])
    print(f"discontinuity picture: {int((np.linalg.norm(disc, axis=2) > 0).sum())} edge pixels; wrote "
          f"{path.relative_to(ROOT)}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--docs", action="store_true", help="write the docs/handheld pictures")
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--only", choices=("decode", "masks", "near"), help="run just one of the issue-16 parts")
    args = parser.parse_args(argv)
    if args.only:
        {"decode": bench_decode, "masks": lambda: bench_masks(args.docs),
         "near": lambda: bench_near_light(args.docs)}[args.only]()
        return
    if not args.skip_speed:
        bench_speed()
    bench_decode()
    bench_diligent(args.docs)
    bench_seitz(args.docs)
    bench_masks(args.docs)
    bench_near_light(args.docs)
    if args.docs:
        docs_discontinuity()


if __name__ == "__main__":
    main()
