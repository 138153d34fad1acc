"""Debug pictures of the feature extractor: patches over the fragment, the dominant orientation
over the normal map (like Fig. 5.5) and the erosion map (like Fig. 5.6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from common.features.erosion import erosion_map
from common.features.patches import MIN_COVERAGE
from common.features.table import FeatureTable, _area_downsample
from common.rgbn.image import RGBNImage


def _show(ax, rgb, pixel_mm):
    h, w = rgb.shape[:2]
    ax.imshow(np.clip(rgb, 0, 1), extent=(-0.5 * pixel_mm, (w - 0.5) * pixel_mm,
                                          (h - 0.5) * pixel_mm, -0.5 * pixel_mm), interpolation="antialiased")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")


def save_debug_pictures(image: RGBNImage, table: FeatureTable, out_dir, *, prefix: str = "",
                        kind: str = "p10", dpi: int = 90) -> list[Path]:
    """Write ``<prefix>patches.png``, ``<prefix>orientation.png`` (when the image has normals)
    and ``<prefix>erosion.png`` (idem) into ``out_dir``; return their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    px = image.pixel_mm
    step = max(1, int(round(table.work_pixel_mm / px)))
    shown_px = px * step
    albedo = image.albedo[::step, ::step]
    idx = table.patch_indices(kind)
    paths = []

    fig, ax = plt.subplots(figsize=(6, 6))
    _show(ax, albedo ** (1 / 2.2), shown_px)
    if len(table.contour_mm):
        c = np.vstack([table.contour_mm, table.contour_mm[:1]])
        ax.plot(c[:, 0], c[:, 1], "-", color="yellow", lw=0.8)
    for i in idx:
        ok = table.patch_coverage[i] >= MIN_COVERAGE
        ax.add_patch(Circle(table.patch_centers_mm[i], 5.0 if kind == "p10" else 10.0, fill=False,
                            ec="cyan" if ok else "red", ls="-" if ok else "--", lw=0.8))
        p, n = table.patch_contour_mm[i], table.patch_normals[i]
        ax.plot([p[0], p[0] + 2 * n[0]], [p[1], p[1] + 2 * n[1]], "-", color="magenta", lw=0.8)
    ax.set_title(f"{kind} patches (red dashed: coverage < {MIN_COVERAGE}), outward normals")
    fig.tight_layout()
    paths.append(out / f"{prefix}patches.png")
    fig.savefig(paths[-1], dpi=dpi)
    plt.close(fig)

    if image.normals is None:
        return paths
    nmap = (image.normals[::step, ::step] + 1) / 2
    nmap[~image.mask[::step, ::step]] = 1.0
    fig, ax = plt.subplots(figsize=(6, 6))
    _show(ax, nmap, shown_px)
    ang = table.patch_column("orient_angle")
    amp = table.patch_column("orient_amplitude")
    amax = np.nanmax(amp[idx]) if len(idx) and np.isfinite(amp[idx]).any() else 1.0
    for i in idx:
        if not np.isfinite(ang[i]):
            continue
        n = table.patch_normals[i]
        # the wave vector: across the strokes; the strokes run perpendicular to it
        a = np.radians(ang[i]) + np.arctan2(n[1], n[0]) + np.pi / 2
        half = 4.5 * (0.3 + 0.7 * amp[i] / amax)
        d = half * np.array([np.cos(a), np.sin(a)])
        c = table.patch_centers_mm[i]
        ax.plot([c[0] - d[0], c[0] + d[0]], [c[1] - d[1], c[1] + d[1]], "-", color="black", lw=1.5)
    ax.set_title("dominant orientation (stroke direction, length ~ amplitude)")
    fig.tight_layout()
    paths.append(out / f"{prefix}orientation.png")
    fig.savefig(paths[-1], dpi=dpi)
    plt.close(fig)

    shape = (-(-image.shape[0] // step), -(-image.shape[1] // step))
    m = image.mask.astype(np.float32)
    M = _area_downsample(m, step, shape)
    safe = np.maximum(M, 1e-6)
    grey_full = image.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    grey = _area_downsample(grey_full * m, step, shape) / safe
    nz = _area_downsample(image.normals[..., 2] * m, step, shape) / safe
    eroded, _, _ = erosion_map(grey, nz, M > 0.5)
    rgb = np.repeat((np.clip(grey, 0, 1) ** (1 / 2.2))[..., None], 3, axis=2)
    rgb[M <= 0.5] = 1.0
    rgb[eroded] = (1.0, 0.1, 0.1)
    fig, ax = plt.subplots(figsize=(6, 6))
    _show(ax, rgb, table.work_pixel_mm)
    ax.set_title(f"cracking/erosion (red), density {table.values.get('erosion_density_s0', np.nan):.3f}")
    fig.tight_layout()
    paths.append(out / f"{prefix}erosion.png")
    fig.savefig(paths[-1], dpi=dpi)
    plt.close(fig)
    return paths
