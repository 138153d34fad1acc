"""A synthetic wall painting, broken into fragments with known ground truth.

:func:`generate_wall` paints a wall (:mod:`~common.synth.painting`), lays relief over the whole
of it (:mod:`~common.synth.relief`), breaks it (:mod:`~common.synth.breakage`), and cuts each
fragment out into its own frame -- rotated by a random angle, its pose -- as an
:class:`~common.rgbn.image.RGBNImage` and a :class:`~common.acquisition.surface.FragmentSurface`,
then deteriorates it (:mod:`~common.synth.deterioration`). Some pieces go missing; a few
spurious fragments from another wall are mixed in. Every fragment layer is evaluated directly at
the wall position of each output pixel, so colour and relief continue exactly across true joins.

Frames: a fragment's frame has x = col * pixel_mm (right), y = row * pixel_mm (down); its pose
``(angle_deg, tx_mm, ty_mm)`` maps it to the wall (x right, y down, mm) by
``wall = R(angle) @ p + t`` with ``R = [[cos, -sin], [sin, cos]]``.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from common.acquisition.surface import FragmentSurface
from common.rgbn.image import RGBNImage
from common.store import content_key
from common.synth import deterioration as det
from common.synth.breakage import Fracture, fracture_recursive, fracture_voronoi
from common.synth.noise import FractalField
from common.synth.painting import Painting, paint_wall, painting_from_image
from common.synth.realistic import (PRESETS, REGION_FRACTION, MaterialLoss, lose_material, paint_plaster,
                                   plaster_palette, recovered_region, round_outline, wall_ground)
from common.synth.relief import WallRelief, normals_from_height

log = logging.getLogger(__name__)

# mean piece area / median size^2 of the recursive model (measured), used to size the wall
_AREA_FACTOR = 1.2


@dataclass
class Fragment:
    """One fragment of a synthetic (or imported) wall.

    Attributes
    ----------
    id : str
        Fragment id (random order: it says nothing about the position on the wall).
    rgbn : RGBNImage or None
        Front face in the fragment's own frame (None when not kept in memory, or after loading
        the ground truth alone).
    surface : FragmentSurface or None
        The physical front face (with its back) for the simulated flatbed.
    pose : (angle_deg, tx_mm, ty_mm) or None
        Fragment frame -> wall; None for a spurious fragment (it belongs to no place here).
    spurious : bool
        True for a fragment from another wall.
    area_mm2 : float
        Area of the (eroded) fragment.
    contour_mm : (M, 2) float array or None
        Outer contour in the fragment frame (x right, y down, mm).
    notes : dict
        How it was deteriorated beyond erosion, pits and cracks: ``fade`` (amount) or
        ``discolour`` (kind) and ``strength``; ground truth only, never in the images.
    """

    id: str
    rgbn: RGBNImage | None = None
    surface: FragmentSurface | None = None
    pose: tuple[float, float, float] | None = None
    spurious: bool = False
    area_mm2: float = float("nan")
    contour_mm: np.ndarray | None = None
    notes: dict = field(default_factory=dict)

    def to_wall(self, p_mm: np.ndarray) -> np.ndarray:
        """Fragment-frame points (N, 2) mm -> wall mm."""
        if self.pose is None:
            raise ValueError(f"fragment {self.id} is spurious and has no pose")
        return pose_apply(self.pose, p_mm)

    def from_wall(self, w_mm: np.ndarray) -> np.ndarray:
        """Wall points (N, 2) mm -> fragment frame mm."""
        if self.pose is None:
            raise ValueError(f"fragment {self.id} is spurious and has no pose")
        a = np.deg2rad(self.pose[0])
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        return (np.asarray(w_mm, float) - np.array(self.pose[1:])) @ R


def pose_apply(pose, p_mm: np.ndarray) -> np.ndarray:
    """Apply a pose ``(angle_deg, tx, ty)`` to (N, 2) points: ``R(angle) @ p + t``."""
    a = np.deg2rad(pose[0])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.asarray(p_mm, float) @ R.T + np.array(pose[1:], float)


@dataclass
class Wall:
    """A broken wall and its ground truth.

    Attributes
    ----------
    id : str
    fragments : list of Fragment
        Delivered fragments (present ones and spurious ones, in random order).
    adjacency : list of (id_a, id_b, shared_length_mm)
        True neighbours among the delivered fragments (id_a < id_b), with the length of the
        crack they shared before erosion.
    correspondences : dict (id_a, id_b) -> ((K, 2), (K, 2))
        Corresponding contour points of each adjacent pair, in each fragment's own frame (mm).
    width_mm, height_mm : float
        Wall size.
    dpi : float
        Sampling of the fragment images.
    n_missing : int
        Pieces of the wall that were broken but not delivered.
    params : dict
        Generation parameters (seed, mode, ...).
    preview : dict
        ``albedo`` (painting at ~1 mm/px), ``labels`` (pieces on the same grid, -1 = lost plaster),
        ``label_ids`` (fragment id of each label, '' for missing pieces), ``grid_mm``.
    """

    id: str
    fragments: list[Fragment]
    adjacency: list[tuple[str, str, float]]
    correspondences: dict
    width_mm: float
    height_mm: float
    dpi: float
    n_missing: int = 0
    params: dict = field(default_factory=dict)
    preview: dict = field(default_factory=dict)

    def fragment(self, fragment_id: str) -> Fragment:
        for f in self.fragments:
            if f.id == fragment_id:
                return f
        raise KeyError(f"no fragment {fragment_id!r} in wall {self.id}")

    def neighbours(self, fragment_id: str) -> list[str]:
        """Ids of the true neighbours of a fragment."""
        return sorted({b if a == fragment_id else a for a, b, _ in self.adjacency if fragment_id in (a, b)})

    def is_neighbour(self, id_a: str, id_b: str) -> bool:
        return tuple(sorted((id_a, id_b))) in {(a, b) for a, b, _ in self.adjacency}


# --------------------------------------------------------------------------------------------
@dataclass
class _Plan:
    painting: Painting
    relief: WallRelief | None
    fracture: Fracture
    loss: MaterialLoss | None = None


@dataclass
class _Look:
    """How fragments are cut out and deteriorated (the same for every fragment of a wall)."""
    erosion_mm: float
    surfaces: bool
    chips_per_cm: float = 0.2
    round_mm: float = 0.0
    colour_only: bool = False
    fade_fraction: float = 0.15
    discolour_fraction: float = 0.15
    realistic: bool = False
    edge_noise_mm: float = 0.0
    surface_wear: bool = True


def _plan(n_pieces: int, rng_paint, rng_relief, rng_break, *, mode, style, image, median_size_mm, sigma,
          jag_mm, aspect=1.5, image_width_mm=None, palette=None, fracture_kw=None, relief_res_mm=0.25,
          relief=True, loss=None, region_rng=None, ground=None) -> _Plan:
    if image is not None:
        aspect = image.shape[1] / image.shape[0]
        width = image_width_mm or np.sqrt(n_pieces * _AREA_FACTOR * median_size_mm ** 2 * aspect)
        painting = painting_from_image(image, width)
        W, H = painting.size_mm
    else:
        area = n_pieces * _AREA_FACTOR * median_size_mm ** 2 / (REGION_FRACTION if region_rng is not None else 1.0)
        H = float(np.sqrt(area / aspect)) + 8.0
        W = float(aspect * (H - 8.0)) + 8.0
        if style == "pompeii":
            painting = paint_plaster(W, H, rng_paint, palette=palette, ground=ground)
        else:
            painting = paint_wall(W, H, rng_paint, style=style)
    wall_relief = WallRelief(painting, rng_relief, res_mm=relief_res_mm) if relief else None
    kw = dict(median_size_mm=median_size_mm, sigma=sigma, n_pieces=n_pieces, jag_mm=jag_mm, **(fracture_kw or {}))
    if region_rng is not None and image is None:
        kw["keep"] = recovered_region(W, H, region_rng)
    fracture = (fracture_recursive if mode == "recursive" else fracture_voronoi)(W, H, rng_break, **kw)
    return _Plan(painting, wall_relief, fracture, loss)


def _render_piece(plan: _Plan, label: int, bbox, dpi: float, rng: np.random.Generator, *, look: _Look,
                  spurious: bool):
    """Cut one piece out of the wall into its own (rotated) frame and deteriorate it.

    Returns (Fragment without id, crack samples {other label: (crack length mm, (K, 2) wall mm)}).
    """
    erosion_mm, surfaces = look.erosion_mm, look.surfaces and not look.colour_only
    pm = 25.4 / dpi
    g = plan.fracture.grid_mm
    (r0, r1), (c0, c1) = bbox
    rr, cc = np.nonzero(plan.fracture.coarse_labels[r0:r1, c0:c1] == label)
    pts = np.column_stack([(cc + c0) * g, (rr + r0) * g])
    angle = float(rng.uniform(0.0, 360.0))
    a = np.deg2rad(angle)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    p = pts @ R  # R^T w: the piece's coarse cells in the fragment frame
    pad = 0.5 + 1.5 * g  # the piece reaches ~1 cell beyond its cell centres, plus sub-mm jags
    off = p.min(axis=0) - pad
    W = int(np.ceil((p[:, 0].max() + pad - off[0]) / pm)) + 1
    H = int(np.ceil((p[:, 1].max() + pad - off[1]) / pm)) + 1
    t = R @ off
    pose = (angle, float(t[0]), float(t[1]))
    G = np.hstack([R * pm, t[:, None]])  # wall = G @ (col, row, 1)
    shape = (H, W)
    labels = plan.fracture.labels_grid(G, shape, near=label)
    mask0 = det.largest_component(labels == label)
    # crack samples: inner boundary pixels of this piece with a 4-neighbour in another piece
    cracks = {}
    if not spurious:
        lab_p = np.pad(labels, 1, constant_values=-1)
        hits_idx, hits_lab = [], []
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            other = lab_p[1 + dr:1 + dr + H, 1 + dc:1 + dc + W]
            sel = mask0 & (other >= 0) & (other != label)
            idx = np.flatnonzero(sel)
            hits_idx.append(idx)
            hits_lab.append(other.ravel()[idx])
        idx = np.concatenate(hits_idx).astype(np.int64)
        lab = np.concatenate(hits_lab).astype(np.int64)
        if idx.size:
            faces = np.bincount(lab)  # pixel faces shared with each other piece
            keys = np.unique(lab * (H * W) + idx)  # (other piece, pixel) pairs, each once
            others, pix_all = keys // (H * W), keys % (H * W)
            for m in np.unique(others):
                pix = pix_all[others == m]
                # a digital curve with n_pix boundary pixels and n_faces boundary faces made
                # n_pix steps along its major axis and n_faces - n_pix across: exact for straight
                # cracks, within ~8 % for any mixture of directions
                length = pm * np.hypot(pix.size, faces[m] - pix.size)
                pts = np.column_stack([pix % W, pix // W, np.ones(pix.size)]) @ G.T  # wall mm
                # about one sample per mm of crack
                cell = np.floor(pts).astype(np.int64)
                _, keep = np.unique(cell[:, 0] * 1_000_003 + cell[:, 1], return_index=True)
                cracks[int(m)] = (float(length), pts[np.sort(keep)])

    albedo = plan.painting.sample_grid(G, shape)
    if look.colour_only:
        height = np.zeros(shape, np.float32)
    else:
        height = plan.relief.height_grid(G, shape)
        back_rough = plan.relief.back_rough.grid(G, shape)
        thick = plan.relief.thickness_grid(G, shape, back_rough=back_rough)
    # deterioration (per fragment: neighbours now differ)
    if look.realistic:
        # plaster lost along each crack (both sides, unevenly), chipped, then worn round
        mask = lose_material(mask0, labels, label, G, plan.loss) if plan.loss is not None else mask0
        mask = det.erode_edges(mask, pm, rng, depth_mm=erosion_mm, chips=look.chips_per_cm)
        noise = None
        if look.edge_noise_mm > 0:
            noise = FractalField(rng, 0.6, octaves=2, persistence=0.7, amplitude=look.edge_noise_mm / pm).grid(
                np.array([[pm, 0.0, 0.0], [0.0, pm, 0.0]]), shape)
        mask = det.largest_component(round_outline(mask, look.round_mm / pm, noise_px=noise))
    else:
        mask = det.erode_edges(mask0, pm, rng, depth_mm=erosion_mm) if erosion_mm > 0 else mask0
    if not mask.any():
        mask = mask0
    if not look.colour_only:
        height = det.wear_edges(height, mask, pm, radius_mm=max(0.3, erosion_mm, look.round_mm))
    if look.surface_wear:
        det.pit_surface(height, albedo, mask, pm, rng)
        det.crack_surface(height, albedo, mask, pm, rng)
    u = rng.random()
    notes = {}
    if u < look.fade_fraction:
        notes["fade"] = float(rng.uniform(0.2, 0.6))
        albedo = det.fade(albedo, notes["fade"])
    elif u < look.fade_fraction + look.discolour_fraction:
        notes["discolour"] = str(rng.choice(sorted(det.DISCOLOURATIONS)))
        notes["strength"] = float(rng.uniform(0.5, 1.0))
        albedo = det.discolour(albedo, notes["discolour"], notes["strength"])
    albedo[~mask] = 0.0
    if look.colour_only:
        rgbn = RGBNImage(albedo=albedo, mask=mask, dpi=dpi, attrs={"source": "synthetic fresco", "face": "front"})
        return _finish(rgbn, None, mask, pm, pose, spurious, notes), cracks
    # normals from the height gradient: x right, y up (towards row 0), z to the viewer
    n = normals_from_height(height, pm)
    n[~mask] = (0.0, 0.0, 1.0)
    med_t = float(np.median(thick[mask]))
    thickness_map = np.where(mask, thick + height - float(np.median(height[mask])), 0.0).astype(np.float32)
    rgbn = RGBNImage(albedo=albedo, mask=mask, dpi=dpi, normals=n, confidence=mask.astype(np.float32),
                     height_mm=thickness_map, attrs={"source": "synthetic fresco", "face": "front",
                                                      "height_meaning": "thickness: front face above back, mm"})
    surface = None
    if surfaces:
        front_h = np.where(mask, height - float(np.median(height[mask])), 0.0).astype(np.float32)
        back_h = np.where(mask, thick - med_t, 0.0).astype(np.float32)
        shade = 1.0 + 0.15 * np.tanh(back_rough)
        back_albedo = np.where(mask[..., None], det.PLASTER[None, None, :] * 0.9 * shade[..., None],
                               0.0).astype(np.float32)
        # the back, as seen after flipping the fragment over about its vertical axis
        back = FragmentSurface(np.fliplr(back_albedo).copy(), np.fliplr(back_h).copy(), np.fliplr(mask).copy(), dpi,
                               thickness_mm=med_t)
        surface = FragmentSurface(albedo, front_h, mask, dpi, thickness_mm=med_t, back=back)
    return _finish(rgbn, surface, mask, pm, pose, spurious, notes), cracks


def _finish(rgbn, surface, mask, pm, pose, spurious, notes) -> Fragment:
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cont = max(contours, key=len).reshape(-1, 2).astype(np.float64) * pm
    return Fragment(id="", rgbn=rgbn, surface=surface, pose=None if spurious else pose, spurious=spurious,
                    area_mm2=float(mask.sum() * pm * pm), contour_mm=cont, notes=notes)


_LEGACY = dict(style="aegean", median_size_mm=30.0, sigma=1.0, missing_fraction=0.2, spurious_fraction=0.05,
               erosion_mm=0.6, jag_mm=1.5, min_shared_mm=3.0)


def generate_wall(n_fragments: int, seed: int, dpi: float = 300, *, mode: str = "recursive",
                  style: str | None = None, image: np.ndarray | None = None, image_width_mm: float | None = None,
                  median_size_mm: float | None = None, sigma: float | None = None,
                  missing_fraction: float | None = None, spurious_fraction: float | None = None,
                  erosion_mm: float | None = None, jag_mm: float | None = None, min_shared_mm: float | None = None,
                  keep_images: bool = True, surfaces: bool = True, workers: int = 1,
                  on_fragment: Callable[[Fragment], None] | None = None,
                  progress: Callable[[float, str], None] | None = None, preset: str | None = None,
                  palette_seed: int | None = None, colour_only: bool = False, gap_median_mm: float | None = None,
                  **preset_overrides) -> Wall:
    """Paint, relieve, break and deteriorate a wall; return its fragments and ground truth.

    Parameters
    ----------
    n_fragments : int
        Number of fragments delivered (present pieces plus spurious ones).
    seed : int
        Same seed and parameters -> identical data.
    dpi : float
        Sampling of the fragment images (pixel = 25.4 / dpi mm).
    mode : {'recursive', 'voronoi'}
        Breakage model: recursive perpendicular splitting (Shin et al. 2012) or a power diagram.
    style : {'aegean', 'roman', 'pompeii'}
        Painting style (ignored with ``image``); default 'aegean' ('pompeii' with that preset).
    image : (H, W, 3) array, optional
        A user-supplied painting (sRGB) instead of the generated one.
    image_width_mm : float, optional
        Physical width of ``image`` on the wall (default: sized for the fragment count).
    median_size_mm, sigma : float
        Log-normal fragment size (square root of area): median and log-sd, clipped to 1-20 cm
        (default 30 mm and 1.0; the 'pompeii' preset 90 mm and 0.4, clipped to 2-20 cm).
    missing_fraction : float
        Fraction of the broken pieces that are lost (0.1-0.3 is typical of excavations).
    spurious_fraction : float
        Fraction of delivered fragments that come from another wall.
    erosion_mm : float
        Mean depth of edge erosion.
    jag_mm : float
        Amplitude of the crack jaggedness.
    min_shared_mm : float
        Pieces sharing less crack than this are not counted as neighbours.
    keep_images : bool
        Keep each fragment's RGBN image and surface in the returned wall (False: only metadata,
        for large walls streamed through ``on_fragment``).
    surfaces : bool
        Build each fragment's :class:`FragmentSurface` (front and back, for the simulated
        flatbed); False when only the RGBN images are wanted (faster).
    on_fragment : callable(Fragment), optional
        Called with each finished fragment (with its images), e.g. to write it to the store.
    progress : callable(fraction, text), optional
        Progress report per fragment.
    workers : int
        Render fragments in this many forked processes (same data as with one).
    preset : {None, 'pompeii'}
        None: the original synthetic fresco (colourful Aegean/Roman painting, cm pieces, sub-mm
        erosion). 'pompeii': looks like RePAIR's real broken Pompeii frescoes -- 2-20 cm pieces,
        plaster lost along every crack (gaps of a few mm, uneven along the crack, see
        :class:`~common.synth.realistic.MaterialLoss`), chipped and rounded outlines, mostly plain
        plaster with sparse faded painting (:func:`~common.synth.realistic.paint_plaster`),
        spurious fragments from another wall of the same palette, neighbours sharing >= 10 mm of
        crack. Explicit arguments override the preset's values.
    palette_seed : int, optional
        'pompeii' style: walls with the same palette seed share one palette (default: ``seed``).
    colour_only : bool
        Fragments without normals, height or surfaces (colour and mask only, like RePAIR);
        faster.
    gap_median_mm : float, optional
        Median gap scale of the material loss (preset 'pompeii': 4.2 mm).
    **preset_overrides
        Further preset values: ``min_size_mm``, ``max_size_mm``, ``jag_scale_mm``,
        ``chips_per_cm``, ``round_mm``, ``edge_noise_mm`` (fine outline roughness),
        ``border_weight`` (how likely a piece on the wall's outer edge is delivered, relative to
        an inner one), ``irregular_area`` (break only an irregular patch of the wall,
        :func:`~common.synth.realistic.recovered_region`), ``surface_wear`` (pits and hairline
        cracks; off in the preset), ``fade_fraction``, ``discolour_fraction``, ``relief_res_mm``, ``loss``
        (None, 'pompeii' or a dict of :class:`~common.synth.realistic.MaterialLoss` arguments).
        ``house_plaster`` (True: the 'pompeii' walls of one ``palette_seed`` share their plaster, each
        wall's tone a little off the house's, :func:`~common.synth.realistic.wall_ground`; default
        False, each wall draws one of the palette's grounds).

    Returns
    -------
    Wall

    References
    ----------
    Thesis §5.3.3 (a painted and broken fresco with known joins); Shin et al. 2012 (fracture
    patterns of Theran wall paintings).

    Examples
    --------
    >>> wall = generate_wall(6, seed=1, dpi=40)
    >>> len(wall.fragments)
    6
    """
    if preset is not None and preset not in PRESETS:
        raise ValueError(f"preset must be None or one of {sorted(PRESETS)}, got {preset!r}")
    known = {"min_size_mm", "max_size_mm", "jag_scale_mm", "chips_per_cm", "round_mm", "fade_fraction",
             "discolour_fraction", "relief_res_mm", "loss", "edge_noise_mm", "border_weight", "irregular_area",
             "surface_wear"}
    # walls of one palette share their plaster (realistic.wall_ground); off unless asked, so the walls made
    # before keep their colours and ids
    house_plaster = bool(preset_overrides.pop("house_plaster", False))
    if set(preset_overrides) - known:
        raise ValueError(f"unknown argument(s) {sorted(set(preset_overrides) - known)}; known: {sorted(known)}")
    base = dict(_LEGACY, **(PRESETS[preset] if preset else {}))
    base.update({k: v for k, v in preset_overrides.items()})
    given = dict(style=style, median_size_mm=median_size_mm, sigma=sigma, missing_fraction=missing_fraction,
                 spurious_fraction=spurious_fraction, erosion_mm=erosion_mm, jag_mm=jag_mm, min_shared_mm=min_shared_mm)
    base.update({k: v for k, v in given.items() if v is not None})
    style, median_size_mm, sigma = base["style"], base["median_size_mm"], base["sigma"]
    missing_fraction, spurious_fraction = base["missing_fraction"], base["spurious_fraction"]
    erosion_mm, jag_mm, min_shared_mm = base["erosion_mm"], base["jag_mm"], base["min_shared_mm"]
    realistic = preset is not None or bool(preset_overrides) or colour_only
    if style not in ("aegean", "roman", "pompeii"):
        raise ValueError(f"style must be 'aegean', 'roman' or 'pompeii', got {style!r}")
    if int(n_fragments) != n_fragments or n_fragments < 1:
        raise ValueError(f"n_fragments must be a positive integer, got {n_fragments}")
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    if mode not in ("recursive", "voronoi"):
        raise ValueError(f"mode must be 'recursive' or 'voronoi', got {mode!r}")
    if not 0 <= missing_fraction < 0.9:
        raise ValueError(f"missing_fraction must be in [0, 0.9), got {missing_fraction}")
    if not 0 <= spurious_fraction < 1:
        raise ValueError(f"spurious_fraction must be in [0, 1), got {spurious_fraction}")
    if image is not None and (np.ndim(image) != 3 or np.shape(image)[2] < 3):
        raise ValueError(f"image must be an (H, W, 3) RGB array, got shape {np.shape(image)}")
    n_fragments = int(n_fragments)
    params = dict(n_fragments=n_fragments, seed=int(seed), dpi=float(dpi), mode=mode, style=style,
                  image=None if image is None else content_key(np.ascontiguousarray(image).tobytes().hex()[:4096],
                                                               str(np.shape(image))),
                  median_size_mm=median_size_mm, sigma=sigma, missing_fraction=missing_fraction,
                  spurious_fraction=spurious_fraction, erosion_mm=erosion_mm, jag_mm=jag_mm)
    loss_kw = None
    if realistic:
        # (the original walls keep their parameters, hence their ids)
        loss_kw = base.get("loss")
        if loss_kw == "pompeii":
            loss_kw = {}
        if loss_kw is not None and gap_median_mm is not None:
            loss_kw = dict(loss_kw, median_mm=float(gap_median_mm))
        params.update(preset=preset, palette_seed=int(seed if palette_seed is None else palette_seed),
                      colour_only=bool(colour_only), min_shared_mm=min_shared_mm, loss=loss_kw,
                      **{k: base.get(k) for k in sorted(known - {"loss"})})
        if house_plaster:
            params["house_plaster"] = True
    wall_id = f"s{int(seed)}n{n_fragments}-{content_key(json.dumps(params, sort_keys=True), length=6)}"
    ss = np.random.SeedSequence(int(seed))
    s_paint, s_relief, s_break, s_choice, s_spur, s_frag = ss.spawn(6)
    n_spur = int(round(spurious_fraction * n_fragments))
    if spurious_fraction > 0 and n_fragments >= 10:
        n_spur = max(n_spur, 1)
    n_present = n_fragments - n_spur
    n_pieces = int(np.ceil(n_present / (1.0 - missing_fraction))) if n_present else 0
    rng_choice = np.random.default_rng(s_choice)

    extra = {}
    if realistic:
        palette = plaster_palette(params["palette_seed"]) if style == "pompeii" else None
        fkw = {k: base[k] for k in ("min_size_mm", "max_size_mm", "jag_scale_mm") if base.get(k) is not None}
        extra = dict(palette=palette, fracture_kw=fkw, relief_res_mm=base.get("relief_res_mm") or 0.25,
                     relief=not colour_only,
                     ground=wall_ground(palette, seed) if house_plaster and palette is not None else None)
        if base.get("irregular_area") and image is None:
            # break a larger wall and keep an irregular patch of it (no straight outer edges)
            extra["region_rng"] = np.random.default_rng([int(seed), 4241])
    plan = _plan(max(n_pieces, 1), np.random.default_rng(s_paint), np.random.default_rng(s_relief),
                 np.random.default_rng(s_break), mode=mode, style=style,
                 image=None if image is None else np.asarray(image), median_size_mm=median_size_mm, sigma=sigma,
                 jag_mm=jag_mm, image_width_mm=image_width_mm,
                 loss=MaterialLoss(int(seed), **loss_kw) if loss_kw is not None else None, **extra)
    coarse = plan.fracture.coarse_labels
    areas = np.bincount(coarse[coarse >= 0].ravel(), minlength=plan.fracture.n_pieces)
    # at least ~5x5 mm (realistic presets: half their smallest size, no slivers of the outer edge)
    min_area = max(25.0, (0.5 * base.get("min_size_mm", 0.0)) ** 2) if realistic else 25.0
    usable = np.nonzero(areas * plan.fracture.grid_mm ** 2 >= min_area)[0]
    if len(usable) < n_present:
        raise ValueError(f"the wall broke into only {len(usable)} usable pieces, fewer than the {n_present} "
                         f"requested; lower median_size_mm or supply a larger image_width_mm")
    if realistic and base.get("border_weight", 1.0) != 1.0:
        # pieces on the wall's outer edge (long straight edges) go missing first
        lab_p = np.pad(coarse, 1, constant_values=-1)
        ring = np.zeros(coarse.shape, bool)
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ring |= lab_p[1 + dr:1 + dr + coarse.shape[0], 1 + dc:1 + dc + coarse.shape[1]] == -1
        border = np.bincount(coarse[ring & (coarse >= 0)], minlength=plan.fracture.n_pieces) > 0
        w = np.where(border[usable], float(base["border_weight"]), 1.0)
        present = np.sort(rng_choice.choice(usable, n_present, replace=False, p=w / w.sum()))
    else:
        present = np.sort(rng_choice.choice(usable, n_present, replace=False))
    jobs = [(plan, int(lab), False) for lab in present]
    if n_spur:
        sr = np.random.default_rng(s_spur)
        # another wall: the other style, or for 'pompeii' another wall of the same palette
        other = "pompeii" if style == "pompeii" else ("roman" if style == "aegean" else "aegean")
        splan = _plan(n_spur + 4, sr, sr, sr, mode=mode, style=other, image=None, median_size_mm=median_size_mm, sigma=sigma, jag_mm=jag_mm,
                      loss=MaterialLoss(int(seed) + 7919, **loss_kw) if loss_kw is not None else None,
                      **dict(extra, ground=wall_ground(extra["palette"], int(seed) + 7919)
                             if extra.get("ground") is not None else None))
        sc = splan.fracture.coarse_labels
        sareas = np.bincount(sc[sc >= 0].ravel(), minlength=splan.fracture.n_pieces)
        cand = np.nonzero(sareas * splan.fracture.grid_mm ** 2 >= min_area)[0]   # the wall's own floor
        jobs += [(splan, int(lab), True) for lab in sr.choice(cand, min(n_spur, len(cand)), replace=False)]
    # ids in random order: an id says nothing about the place on the wall
    numbers = rng_choice.permutation(len(jobs)) + 1
    ids = [f"{wall_id}-{k:03d}" for k in numbers]

    frags: list[Fragment] = []
    crack_by_label: dict[int, dict] = {}
    label_of: dict[str, int] = {}
    frag_seeds = s_frag.spawn(len(jobs))
    tasks = []
    for j, (pl, lab, spur) in enumerate(jobs):
        sl = ndimage.find_objects((pl.fracture.coarse_labels == lab).astype(np.int32))[0]
        tasks.append((j, ((sl[0].start, sl[0].stop), (sl[1].start, sl[1].stop))))
    global _POOL_STATE
    look = _Look(erosion_mm=erosion_mm, surfaces=surfaces)
    if realistic:
        look = _Look(erosion_mm=erosion_mm, surfaces=surfaces and not colour_only,
                     chips_per_cm=base.get("chips_per_cm", 0.2), round_mm=base.get("round_mm") or 0.0,
                     colour_only=colour_only, fade_fraction=base.get("fade_fraction", 0.15),
                     discolour_fraction=base.get("discolour_fraction", 0.15), realistic=True,
                     edge_noise_mm=base.get("edge_noise_mm") or 0.0, surface_wear=base.get("surface_wear", True))
    _POOL_STATE = (jobs, frag_seeds, float(dpi), look)
    pool = None
    try:
        if workers > 1 and len(jobs) > 1 and "fork" in mp.get_all_start_methods():
            # forked workers inherit the wall plan; each fragment has its own seed -> same data
            pool = mp.get_context("fork").Pool(min(workers, len(jobs)))
            results = pool.imap(_render_task, tasks)
        else:
            results = map(_render_task, tasks)
        for j, (frag, cracks) in enumerate(results):
            _, lab, spur = jobs[j]
            fid = ids[j]
            frag.id = fid
            if not spur:
                crack_by_label[lab] = cracks
                label_of[fid] = lab
            if on_fragment is not None:
                on_fragment(frag)
            if not keep_images:
                frag.rgbn = None
                frag.surface = None
            frags.append(frag)
            if progress is not None:
                progress((j + 1) / len(jobs), f"fragment {fid} ({j + 1}/{len(jobs)})")
    finally:
        if pool is not None:
            pool.terminate()
        _POOL_STATE = None

    gap_mm = 0.0 if plan.loss is None else 4.0 * plan.loss.median_mm
    adjacency, corr = _ground_truth(frags, label_of, crack_by_label, min_shared_mm, erosion_mm, gap_mm)
    order = np.argsort([f.id for f in frags])
    frags = [frags[i] for i in order]
    id_of_label = {lab: fid for fid, lab in label_of.items()}
    g = plan.fracture.grid_mm
    step = max(1, int(round(1.0 / plan.painting.res_mm * g)))
    preview = dict(albedo=plan.painting.albedo[::step, ::step].copy(), labels=coarse.copy(), grid_mm=g,
                   label_ids=[id_of_label.get(i, "") for i in range(plan.fracture.n_pieces)])
    W, H = plan.painting.size_mm
    n_missing = (len(usable) if realistic else plan.fracture.n_pieces) - n_present
    return Wall(wall_id, frags, adjacency, corr, W, H, float(dpi), n_missing=n_missing,
                params=params, preview=preview)


_POOL_STATE = None


def _render_task(task):
    j, bbox = task
    jobs, seeds, dpi, look = _POOL_STATE
    pl, lab, spur = jobs[j]
    return _render_piece(pl, lab, bbox, dpi, np.random.default_rng(seeds[j]), look=look, spurious=spur)


def _ground_truth(frags, label_of, crack_by_label, min_shared_mm, erosion_mm, gap_mm=0.0):
    """Adjacency (shared crack length) and contour correspondences of the present pieces."""
    by_id = {f.id: f for f in frags}
    id_of_label = {lab: fid for fid, lab in label_of.items()}
    trees = {}
    adjacency, corr = [], {}
    done = set()
    max_gap = 3.0 * erosion_mm + 2.5 + 2.0 + gap_mm  # erosion, chips, edge wear, lost material
    for la, cracks in crack_by_label.items():
        for lb, (len_ab, pts) in cracks.items():
            if lb not in id_of_label or (min(la, lb), max(la, lb)) in done:
                continue
            done.add((min(la, lb), max(la, lb)))
            ida, idb = id_of_label[la], id_of_label[lb]
            fa, fb = by_id[ida], by_id[idb]
            back = crack_by_label.get(lb, {}).get(la)
            # both sides measured the crack: average them
            length = 0.5 * (len_ab + (back[0] if back else len_ab))
            if length < min_shared_mm:
                continue
            for f in (fa, fb):
                if f.id not in trees:
                    trees[f.id] = cKDTree(f.to_wall(f.contour_mm))
            da, ia = trees[ida].query(pts)
            db, ib = trees[idb].query(pts)
            ok = (da < max_gap) & (db < max_gap)
            pa, pb = fa.contour_mm[ia[ok]], fb.contour_mm[ib[ok]]
            if ida > idb:
                ida, idb, pa, pb = idb, ida, pb, pa
            adjacency.append((ida, idb, float(length)))
            corr[(ida, idb)] = (pa, pb)
    adjacency.sort()
    return adjacency, corr

