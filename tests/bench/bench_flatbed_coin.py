"""The real coin (../shared/data/flatbed-coin) through the generic path: import, nominal calibration, solver.

    python tests/bench/bench_flatbed_coin.py [--figures docs/flatbed] [--store DIR]

What a user with four whole-platen scans from an unknown flatbed does (docs/flatbed.md):

1. ``tessera import scans raw_0.png raw_90.png raw_180.png raw_270.png --crop --fragment coin
   --device coin-flatbed`` (dpi from the files' pHYs): the coin is found by what changes between the
   scans, its mask by focus (it is the bed's own grey, see ``face_masks``), the turn direction
   detected, and the side the lamp lights from read from the shadows (logged and stored in the
   artifact's provenance);
2. ``tessera calibrate --nominal --lamp-direction-deg D --device coin-flatbed``: no target scans of
   that scanner exist, so the simulator's nominal lamp model is turned to that side;
3. the solver service's handler on the ``fragment.ready``.

Reported: the mask against a hand-checked reference (``docs/flatbed/coin_reference_mask.png``, made
once, see docs/flatbed.md), the registration (measured rotations, correlation, residual of the
normalised registration images), the re-rendering residual per scan, wall and CPU time, and
pictures (scans with the mask, albedo, normals, re-rendered vs scanned).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data" / "flatbed-coin"
REFERENCE = ROOT / "docs" / "flatbed" / "coin_reference_mask.png"
DEVICE = "coin-flatbed"


class _Ctx:
    config, log = {}, logging.getLogger("bench")

    def progress(self, *a):
        pass


def run(store_dir: Path, figures: Path | None = None) -> dict:
    from common.acquisition.capture import read_scans
    from common.acquisition.flatbed_normals import rerender
    from common.messages import new_message
    from common.rgbn.image import load_rgbn
    from common.store import Store
    from services import solver
    from services.cli import main

    files = [str(DATA / f"raw_{r}.png") for r in (0, 90, 180, 270)]
    res: dict = {"load_before": os.getloadavg()}
    t0, c0 = time.perf_counter(), time.process_time()
    rc = main(["import", "scans", *files, "--crop", "--fragment", "coin", "--device", DEVICE,
               "--store", str(store_dir)])
    res["import"] = {"exit": rc, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    if rc != 0:
        raise SystemExit(f"import scans failed (exit {rc})")
    store = Store(store_dir)
    [art] = sorted((store_dir / "fragments" / "coin" / "scans").glob("scans-*.h5"))
    ref = store.ref(str(art.relative_to(store_dir)))
    cap = read_scans(store, ref)
    with __import__("h5py").File(art, "r") as f:
        prov = json.loads(f.attrs["provenance"]) if "provenance" in f.attrs else {}
    check = prov.get("registration_check", {}).get("front", {})
    res["registration"] = check
    lamp = check["lamp_direction_deg"]
    rc = main(["calibrate", "--set", f'storage.root="{store_dir}"', "--nominal", "--lamp-direction-deg", str(lamp),
               "--device", DEVICE])
    if rc != 0:
        raise SystemExit("nominal calibration failed")
    t0, c0 = time.perf_counter(), time.process_time()
    ctx = _Ctx()
    ctx.store = store
    events = solver.handle(new_message("fragment.ready", fragment="coin", artifact=ref), ctx)
    res["solve"] = {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}
    img = load_rgbn(store, events[0]["artifact"])
    res["mask_method"] = str(img.attrs.get("mask_method"))
    res["rerender_residual_per_scan"] = [round(float(v), 4) for v in img.attrs["rerender_residual_per_scan"]]
    res["registration_residual"] = float(img.attrs["registration_residual"])
    res["registration_correlation_min"] = float(img.attrs["registration_correlation_min"])
    res["coin_px"] = int(img.mask.sum())
    # the mask against the hand-checked reference, in raw_0's frame (the crop's offset from the artifact)
    scan0 = cap.scans["front"][0]
    x0, y0 = scan0.area_mm[0], scan0.area_mm[1]
    dpi = scan0.dpi
    c0_, r0_ = int(round(x0 * dpi / 25.4)), int(round(y0 * dpi / 25.4))
    if REFERENCE.exists():
        refm = cv2.imread(str(REFERENCE), cv2.IMREAD_GRAYSCALE) > 127
        full = np.zeros_like(refm)
        H, W = img.mask.shape
        full[r0_:r0_ + H, c0_:c0_ + W] = img.mask
        inter, union = np.count_nonzero(full & refm), np.count_nonzero(full | refm)
        res["mask_iou"] = inter / union
        res["mask_area_ratio"] = np.count_nonzero(full) / np.count_nonzero(refm)
    res["dpi"] = dpi
    res["lamp_direction_deg"] = lamp
    res["outline_distance_px"] = outline_agreement([s.image for s in cap.scans["front"]], dpi,
                                                   [s.rotation for s in cap.scans["front"]])
    if figures is not None:
        figures.mkdir(parents=True, exist_ok=True)
        H, W = img.mask.shape
        scans = [s.image for s in cap.scans["front"]]
        # the mask on scan 0 (target frame)
        v = cv2.cvtColor(np.ascontiguousarray(scans[0]), cv2.COLOR_RGB2BGR)
        cnt, _ = cv2.findContours(img.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(v, cnt, -1, (255, 0, 255), 1)
        if REFERENCE.exists():
            cnt, _ = cv2.findContours(refm[r0_:r0_ + H, c0_:c0_ + W].astype(np.uint8), cv2.RETR_EXTERNAL,
                                      cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(v, cnt, -1, (0, 255, 0), 1)
        ys, xs = np.nonzero(img.mask)
        pad = 12
        sl = np.s_[max(0, ys.min() - pad):ys.max() + pad, max(0, xs.min() - pad):xs.max() + pad]
        big = lambda a: cv2.resize(a[sl], None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
        alb = np.clip(img.albedo / max(np.percentile(img.albedo[img.mask], 99), 1e-6), 0, 1) ** (1 / 2.2)
        alb = (alb * 255).astype(np.uint8)[..., ::-1].copy()
        alb[~img.mask] = 0
        nrm = ((img.normals + 1) / 2 * 255).astype(np.uint8)[..., ::-1].copy()
        nrm[~img.mask] = 0
        cv2.imwrite(str(figures / "coin_generic_mask_albedo_normals.png"), np.hstack([big(v), big(alb), big(nrm)]))
        # scanned (registered into scan 0's frame, as the solver registers them) vs re-rendered, per scan
        from common.acquisition.calibration import newest_calibration
        from common.acquisition.locate import face_masks
        from common.acquisition.registration import register_scans, warp_to_target
        cal, _ = newest_calibration(store, DEVICE)
        masks, _ = face_masks(scans, dpi)
        rg = register_scans(scans, dpi, nominal_deg=[s.rotation for s in cap.scans["front"]], masks=masks)
        pred = rerender(img, [r.angle_deg for r in rg], cal.a)
        tiles = []
        for k, s in enumerate(scans):
            obs = warp_to_target(s, rg[k], (H, W))
            top = np.clip(obs, 0, 1)
            bot = np.clip(pred[k], 0, 1)
            t = (np.vstack([top, bot]) ** (1 / 2.2) * 255).astype(np.uint8)[..., ::-1].copy()
            m2 = np.vstack([img.mask, img.mask])
            t[~m2] //= 3
            sl2 = np.s_[max(0, ys.min() - pad):ys.max() + pad, max(0, xs.min() - pad):xs.max() + pad]
            tiles.append(np.vstack([t[:H][sl2], t[H:][sl2]]))
        cv2.imwrite(str(figures / "coin_generic_rerender.png"),
                    cv2.resize(np.hstack(tiles), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST))
    res["load_after"] = os.getloadavg()
    return res


def outline_agreement(scans, dpi, nominal_deg) -> list:
    """Registration in pixels without ground truth: each scan's mask warped into scan 0's frame
    with the solver's registration, against scan 0's mask — the mean distance between their
    outlines (px), per scan. It bounds the registration error plus the masks' own outline noise."""
    from common.acquisition.flatbed_normals import register_face

    _, regs, _, method = register_face(scans, dpi, nominal_deg=nominal_deg)
    from common.acquisition.locate import focus_mask, fragment_mask
    masks = [(focus_mask if method == "focus" else fragment_mask)(s, dpi) for s in scans]
    H, W = masks[0].shape

    def outline(m):
        m8 = m.astype(np.uint8)
        return (m8 - cv2.erode(m8, np.ones((3, 3), np.uint8))) > 0

    def dist_to(m):
        return cv2.distanceTransform((~outline(m)).astype(np.uint8), cv2.DIST_L2, 5)

    out = []
    d0 = dist_to(masks[0])
    for m, r in zip(masks[1:], regs[1:]):
        w = cv2.warpAffine(m.astype(np.uint8), r.affine, (W, H), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
        a = d0[outline(w)].mean()
        b = dist_to(w)[outline(masks[0])].mean()
        out.append(round(float((a + b) / 2), 2))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--figures", type=Path, help="write PNG figures to this folder")
    ap.add_argument("--store", type=Path, help="storage root to use (default: a temporary folder)")
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"skipped: {DATA} not present")
        return 0
    logging.basicConfig(level=logging.WARNING)
    store = args.store or Path(tempfile.mkdtemp(prefix="bench-coin-"))
    res = run(store, args.figures)
    print(json.dumps(res, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
