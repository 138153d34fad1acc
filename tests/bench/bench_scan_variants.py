"""How much do the matching figures depend on how the pieces were scanned? A placed collection written again
the way other scanners and cameras would record it, each variant ranked as ``tessera evaluate --collection``.

Real collections reach the station from other labs: scanned or photographed on a plain background instead of cut
out with an alpha channel, with sensor noise, a little defocus, saved as JPEG. The pieces are the same, so the
figures should be too. Each variant is written from the collection's RGBA pictures (alpha = the piece's coverage
of each pixel, RePAIR's soft edge):

- ``published``: the pictures as they are;
- ``noise``: sensor noise of ``--noise`` grey levels (sRGB, Gaussian) on the colour, alpha kept;
- ``blur+noise``: a defocus blur of ``--blur`` px (linear light) then that noise, alpha kept;
- ``black`` / ``white``: no alpha — the piece mixed with a plain black / off-white (240, 238, 232) background in
  linear light by its alpha, blurred and noised: the mask comes from the background
  (:func:`common.imports.fragments.background_mask`, edge at half coverage);
- ``black-jpeg``: ``black`` saved as JPEG of quality 90.

Every variant is counted against the published collection's neighbour pairs
(:func:`common.matching.report.evaluate_collection` ``adjacency=``), so only the matcher's inputs differ, and
ranked with one bootstrap model (the station's default; nothing fitted on the collection). Printed: within-object
recall @1 / @3, pooled top-5, pair AP, pose accuracy and CPU per variant; ``--picture`` draws them as bars.
About 70 s CPU per variant on RePAIR; the variants are written under ``--work`` (a temporary folder by default).

Run::

    python tests/bench/bench_scan_variants.py [--collection ../shared/data/repair-dev] [--dpi 150]
        [--variants published noise blur+noise black white black-jpeg] [--noise 2] [--blur 1]
        [--picture docs/matching/scan_variants.png] [--json FILE]

Measured (session 19, docs/matching.md "Scanner noise, not the mask, was most of it").
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from common.rgbn.io import linear_to_srgb, srgb_to_linear  # noqa: E402

VARIANTS = ("published", "noise", "blur+noise", "black", "white", "black-jpeg")
BACKGROUNDS = {"black": (0, 0, 0), "white": (240, 238, 232), "black-jpeg": (0, 0, 0)}


def scanned(rgba: np.ndarray, variant: str, *, noise: float, blur_px: float, rng) -> np.ndarray:
    """One RGBA picture (uint8, RGB order) as ``variant`` records it: RGBA or RGB uint8."""
    rgb = rgba[..., :3].astype(np.float32) / 255.0
    alpha = rgba[..., 3:4].astype(np.float32) / 255.0
    if variant == "published":
        return rgba
    lin = srgb_to_linear(rgb)
    if variant in BACKGROUNDS:   # the piece covers each pixel by its alpha: a mix in linear light
        back = srgb_to_linear(np.float32(BACKGROUNDS[variant]) / 255.0)
        lin = lin * alpha + back[None, None] * (1.0 - alpha)
    if variant != "noise" and blur_px > 0:
        lin = cv2.GaussianBlur(lin, (0, 0), blur_px)
    enc = linear_to_srgb(lin) * 255.0 + rng.normal(0.0, noise, lin.shape)
    out = np.clip(enc + 0.5, 0, 255).astype(np.uint8)
    return out if variant in BACKGROUNDS else np.dstack([out, rgba[..., 3]])


def write_variant(src: Path, dst: Path, variant: str, *, noise: float, blur_px: float, seed: int = 7) -> Path:
    """The collection at ``src`` written to ``dst`` as ``variant`` (truth rows name pictures by their stems)."""
    rng = np.random.default_rng(seed)
    for obj in sorted(p for p in src.iterdir() if p.is_dir()):
        out = dst / obj.name
        out.mkdir(parents=True, exist_ok=True)
        if (obj / "truth.csv").is_file():
            with open(obj / "truth.csv", newline="") as fh, open(out / "truth.csv", "w", newline="") as to:
                rows = list(csv.DictReader(fh))
                w = csv.DictWriter(to, ["rpf", "x", "y", "rot"])
                w.writeheader()
                w.writerows({**{k: r[k] for k in ("x", "y", "rot")}, "rpf": Path(r["rpf"]).stem} for r in rows)
        for png in sorted(obj.glob("*.png")):
            bgra = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
            if bgra is None or bgra.ndim != 3 or bgra.shape[2] != 4:
                raise ValueError(f"{png}: expected an RGBA picture (the variants are made from its alpha)")
            pic = scanned(bgra[..., [2, 1, 0, 3]], variant, noise=noise, blur_px=blur_px, rng=rng)
            bgr = pic[..., [2, 1, 0, 3]] if pic.shape[2] == 4 else pic[..., ::-1]
            if variant.endswith("-jpeg"):
                cv2.imwrite(str(out / f"{png.stem}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
            else:
                cv2.imwrite(str(out / png.name), bgr)
    return dst


def picture(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["variant"] for r in rows]
    keys = (("within@1", "within-object recall @1"), ("within@3", "@3"), ("pooled@5", "pooled top-5"),
            ("pair_ap", "pair AP"), ("pose", "pose accuracy"))
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(9, 4))
    for i, (k, label) in enumerate(keys):
        ax.bar(x + (i - 2) * 0.16, [r[k] for r in rows], 0.16, label=label)
    ax.set_xticks(x, names)
    ax.set_ylim(0, 1.05)
    ax.set_title("The same pieces scanned otherwise: matching figures per variant")
    ax.legend(fontsize=8, ncol=5, loc="upper center", bbox_to_anchor=(0.5, -0.1))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--collection", default=str(Path(__file__).resolve().parents[3] / "shared" / "data" / "repair-dev"))
    p.add_argument("--dpi", type=float, default=150.0)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    p.add_argument("--noise", type=float, default=2.0, help="sensor noise, grey levels of 255 (default 2)")
    p.add_argument("--blur", type=float, default=1.0, help="defocus blur sigma, px (default 1)")
    p.add_argument("--work", help="folder for the variants (default: a temporary one, removed)")
    p.add_argument("--picture", help="PNG of the figures per variant")
    p.add_argument("--json", help="write the figures as JSON")
    args = p.parse_args(argv)

    from common.matching.collection import collection_wall
    from common.matching.online import bootstrap_model
    from common.matching.report import evaluate_collection

    src = Path(args.collection)
    pairs = collection_wall(src, dpi=args.dpi).adjacency
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="scan-variants-"))
    print(f"collection {src}: {len(pairs)} true neighbour pairs; variants under {work}", flush=True)
    model = bootstrap_model()
    rows = []
    print(f"{'variant':<12} {'within@1':>8} {'@3':>6} {'pooled@5':>8} {'pair AP':>8} {'pose':>6} {'CPU s':>6}")
    try:
        for v in args.variants:
            t = time.process_time()
            path = src if v == "published" else write_variant(src, work / v, v, noise=args.noise, blur_px=args.blur)
            r = evaluate_collection(path, dpi=args.dpi, model=model, adjacency=pairs)
            row = {"variant": v, "within@1": r["within_object_recall"][1], "within@3": r["within_object_recall"][3],
                   "pooled@5": r["pooled_topk"][5], "pair_ap": r["pair_ap"], "pose": r["pose_accuracy"],
                   "cpu_s": time.process_time() - t}
            rows.append(row)
            print(f"{v:<12} {row['within@1']:8.3f} {row['within@3']:6.3f} {row['pooled@5']:8.3f} {row['pair_ap']:8.3f} "
                  f"{row['pose']:6.3f} {row['cpu_s']:6.0f}", flush=True)
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    if args.picture:
        picture(rows, Path(args.picture))
        print(f"picture: {args.picture}")
    if args.json:
        Path(args.json).write_text(json.dumps({"collection": str(src), "dpi": args.dpi, "noise": args.noise,
                                               "blur_px": args.blur, "model": model.version, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
