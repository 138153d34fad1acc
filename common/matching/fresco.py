"""Which fresco a fragment comes from: a fragment-level signature and a same-fresco likelihood ratio.

Stage 3 (docking, paint across the crack) re-orders candidates by evidence that does not know which
fresco a piece belongs to, so a painted piece of another fresco gains as much as a true neighbour
(docs/matching.md, "Real fragments: RePAIR"). Pieces of one fresco share its plaster (the intonaco:
one lime mix, one ageing, one burial) and its palette; pieces of frescoes of one house share the
palette but less of the plaster. This module describes a fragment by what it shows of both and turns
the comparison of two fragments into a log-likelihood ratio *same fresco vs different frescoes*.

- :class:`FrescoSignature` -- plaster colour (median CIELAB of the unpainted samples), its spread,
  the share of painted samples, the palette (the painted colours present, as a few clusters), the
  face's mean colour and the histogram of the samples' (a*, b*);
- :func:`chroma_distance` -- Bhattacharyya distance of two a*b* histograms: the statistic that tells
  frescoes apart best, on RePAIR as on the factory's walls (AUC 0.78 / 0.80 from boundary profiles;
  docs/matching.md, "Which fresco a piece comes from");
- :func:`lab_signature` -- the signature of a set of CIELAB samples of one fragment;
- :func:`image_signature` -- from a fragment image (every pixel of the face, 1 mm inside the edge);
- :func:`profile_signature` -- from the boundary profile the matcher's index keeps (the colour 0.8
  and 1.6 mm inside the outline, one sample per mm; features schema 2), so the index needs nothing new;
- :func:`grain_energies` -- texture of the plaster: band energies of lightness at a few scales (for
  the measurements; not in the ratio, which the profile cannot give);
- :func:`pair_features` -- the differences of two signatures the ratio is built on;
- :func:`fit_fresco_llr` -- the calibrated ratio, a logistic regression of *same fresco* on pair
  features (:data:`LLR_FEATURES`: the histogram distance) over pairs of fragments of synthetic
  multi-wall collections, minus the training prior log odds (so it is a log-likelihood ratio,
  independent of how many pairs of each kind were drawn);
- :func:`fresco_llr` -- the ratio of two signatures under fitted parameters (:data:`FRESCO_LLR`);
- :func:`with_fresco` -- a join probability with the ratio added to its logit.

The plaster/painted split follows :mod:`common.synth.stats` (plain plaster: chroma ``C* < 8``,
lightness ``L* > 45``; painted: ``C* >= 15``). The combination is naive Bayes over independent
evidence (the ratio adds to the join's logit), as the ribbon and paint evidence are combined in
:mod:`common.matching.index`; calibration of a score into a likelihood ratio by logistic regression
follows Brümmer & du Preez, *Application-independent evaluation of speaker detection*, Computer
Speech & Language 20 (2006), section 4 (prior-free log-likelihood ratio = logit − prior log odds).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: chroma below which (and lightness above :data:`PLAIN_MIN_L`) a sample is plain plaster
PLAIN_CHROMA = 8.0
PLAIN_MIN_L = 45.0
#: chroma from which a sample is painted
PAINTED_CHROMA = 15.0
#: painted colours closer than this (ΔE*ab) are one palette colour
PALETTE_RADIUS_DE = 10.0
#: at most this many palette colours per fragment (the commonest)
PALETTE_MAX = 6
#: a palette colour needs at least this share of the fragment's painted samples
PALETTE_MIN_SHARE = 0.05
#: distance (ΔE) given to a palette colour with no counterpart, and the palette distance's ceiling
PALETTE_CEILING_DE = 40.0
#: names of :func:`pair_features`' columns
PAIR_FEATURES = ("chroma_bhattacharyya", "d_plaster_L", "d_plaster_ab", "d_spread_L", "d_face_L", "d_face_ab",
                 "palette_de", "both_painted")
#: pair features that are differences: a larger one can only lower the ratio (:func:`fit_fresco_llr`)
_DIFFERENCES = (0, 1, 2, 3, 4, 5, 6)
#: the pair features the ratio uses (chosen on synthetic collections: tests/bench/bench_fresco.py)
LLR_FEATURES = ("chroma_bhattacharyya",)
#: the a*b* histogram of a signature: bins of this width (CIELAB units) over [CHROMA_LO, CHROMA_HI)
#: (samples outside fall in the edge bins)
CHROMA_BIN = 1.0
CHROMA_LO, CHROMA_HI = -12.0, 36.0

#: the same-fresco ratio's parameters (:func:`fit_fresco_llr`), fitted on synthetic multi-wall
#: collections only (``python tests/bench/bench_fresco.py --fit``; never on RePAIR): feature means
#: and scales, coefficients, intercept less the training prior log odds, and the clip of the ratio
FRESCO_LLR: dict | None = {"features": ["chroma_bhattacharyya"], "mean": [1.2454], "scale": [1.8067],
                            "coef": [-3.0585], "intercept": -0.9581, "clip": 4.0, "n_same": 1680, "n_different": 5400}
#: the ranking (:meth:`common.matching.index.MatchIndex.rank`) adds this × the ratio to a candidate's logit
#: after stage 2½ (1 would be naive Bayes; 0: off). 4 was the best of 0/1/2/4 for pooled top-5 on two synthetic
#: one-house collections, still rising (docs/matching.md "Which fresco"); 8 (session 25, "The same-fresco ratio's
#: weight above 4"): pooled top-5 of four fresh collections of six walls sharing a palette 0.506 -> 0.545 (mean),
#: at a cost on one figure painting (the thesis-style wall 0.469 -> 0.427, DAFNE 0.438 -> 0.429)
FRESCO_WEIGHT = 8.0


@dataclass
class FrescoSignature:
    """What a fragment shows of its fresco.

    Attributes
    ----------
    plaster_lab : (3,) float
        Median CIELAB (L* 0-100, D65) of the plain plaster samples (all samples' median when fewer
        than :data:`FrescoSignature.min_plaster` are plain).
    plaster_spread_l : float
        Robust spread of the plaster's lightness: 1.4826 × median absolute deviation, L* units.
    painted_share : float
        Share of the samples that are painted (``C* >= 15``).
    palette_lab : (K, 3) float
        The painted colours present (K <= 6 cluster centres, CIELAB), commonest first; empty when
        the fragment shows no paint.
    palette_share : (K,) float
        Share of the painted samples in each palette colour.
    n_samples : int
        Samples the signature was made from.
    face_lab : (3,) float
        CIELAB of the mean colour (linear RGB) of the whole face, paint included; NaN when unknown.
    chroma_hist : (B, B) float32
        Histogram of all samples' (a*, b*) in :data:`CHROMA_BIN` bins over
        ``[CHROMA_LO, CHROMA_HI)``, summing to 1: the plaster's tint and its mottling, and the paint.
    """

    plaster_lab: np.ndarray
    plaster_spread_l: float
    painted_share: float
    palette_lab: np.ndarray
    palette_share: np.ndarray
    n_samples: int
    face_lab: np.ndarray = None
    chroma_hist: np.ndarray = None

    def __post_init__(self):
        if self.face_lab is None:
            self.face_lab = np.full(3, np.nan)

    min_plaster = 10


def _lab_from_linear(rgb_linear: np.ndarray) -> np.ndarray:
    """CIELAB (D65, L* 0-100) of linear RGB in [0, 1], any leading shape."""
    a = np.clip(np.asarray(rgb_linear, np.float32), 0.0, 1.0)
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * np.power(a, 1 / 2.4) - 0.055).astype(np.float32)
    shp = srgb.shape
    return cv2.cvtColor(srgb.reshape(-1, 1, 3), cv2.COLOR_RGB2Lab).reshape(shp)


def _lab_from_srgb8(rgb8: np.ndarray) -> np.ndarray:
    shp = np.shape(rgb8)
    lab = cv2.cvtColor(np.asarray(rgb8).reshape(-1, 1, 3).astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    return lab.reshape(shp)


def _palette(lab: np.ndarray, rng_seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Greedy clustering of painted samples into colours ``PALETTE_RADIUS_DE`` wide, commonest first."""
    if len(lab) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    # a fixed subsample keeps the cost bounded for whole images
    if len(lab) > 4000:
        lab = lab[np.random.default_rng(rng_seed).choice(len(lab), 4000, replace=False)]
    left = np.asarray(lab, np.float64)
    centres, counts = [], []
    n = len(left)
    while len(left) and len(centres) < PALETTE_MAX:
        # the densest sample (most neighbours within the radius) seeds the next colour
        sub = left if len(left) <= 1500 else left[:: int(np.ceil(len(left) / 1500))]
        d = np.linalg.norm(sub[:, None, :] - sub[None, :, :], axis=2)
        seed = sub[np.argmax((d < PALETTE_RADIUS_DE).sum(axis=1))]
        near = np.linalg.norm(left - seed, axis=1) < PALETTE_RADIUS_DE
        members = left[near]
        centre = np.median(members, axis=0)
        if near.sum() / n < PALETTE_MIN_SHARE:
            break
        centres.append(centre)
        counts.append(near.sum())
        left = left[~near]
    if not centres:
        return np.zeros((0, 3)), np.zeros(0)
    counts = np.asarray(counts, float)
    return np.asarray(centres), counts / counts.sum()


def lab_signature(lab: np.ndarray) -> FrescoSignature:
    """The fresco signature of one fragment from its CIELAB samples.

    Parameters
    ----------
    lab : (N, 3) array
        CIELAB samples of the fragment's face (L* 0-100); non-finite rows are ignored.

    Returns
    -------
    FrescoSignature

    Examples
    --------
    >>> s = lab_signature(np.tile([70.0, 2.0, 6.0], (50, 1)))
    >>> s.plaster_lab.round(1).tolist(), s.painted_share
    ([70.0, 2.0, 6.0], 0.0)
    """
    lab = np.asarray(lab, np.float64).reshape(-1, 3) if np.size(lab) else np.zeros((0, 3))
    lab = lab[np.all(np.isfinite(lab), axis=1)]
    if len(lab) < 3:
        raise ValueError(f"a fresco signature needs at least 3 colour samples, got {len(lab)}")
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    plain = (chroma < PLAIN_CHROMA) & (lab[:, 0] > PLAIN_MIN_L)
    ground = lab[plain] if plain.sum() >= FrescoSignature.min_plaster else lab
    med = np.median(ground, axis=0)
    spread = 1.4826 * float(np.median(np.abs(ground[:, 0] - med[0])))
    painted = chroma >= PAINTED_CHROMA
    pal, share = _palette(lab[painted])
    return FrescoSignature(med, spread, float(painted.mean()), pal, share, int(len(lab)),
                           chroma_hist=chroma_histogram(lab))


def chroma_histogram(lab: np.ndarray) -> np.ndarray:
    """Normalised 2-D histogram of CIELAB samples' (a*, b*) (:data:`CHROMA_BIN` bins, edge bins open)."""
    lab = np.asarray(lab, np.float64).reshape(-1, 3)
    nb = int(round((CHROMA_HI - CHROMA_LO) / CHROMA_BIN))
    k = np.clip(np.floor((lab[:, 1:] - CHROMA_LO) / CHROMA_BIN).astype(int), 0, nb - 1)
    h = np.bincount(k[:, 0] * nb + k[:, 1], minlength=nb * nb).astype(np.float32)
    return (h / max(h.sum(), 1.0)).reshape(nb, nb)


def chroma_distance(a: FrescoSignature, b: FrescoSignature) -> float:
    """Bhattacharyya distance ``−ln Σ √(h_a h_b)`` of two signatures' a*b* histograms (0: the same
    distribution; capped at 10 for disjoint ones) — Bhattacharyya, Bull. Calcutta Math. Soc. 35 (1943);
    as a histogram distance for colour, Comaniciu, Ramesh & Meer, CVPR 2000."""
    bc = float(np.sqrt(a.chroma_hist * b.chroma_hist).sum())
    return float(min(-np.log(max(bc, 1e-300)), 10.0))


def image_signature(rgba: np.ndarray, pixel_mm: float, *, inset_mm: float = 1.0) -> FrescoSignature:
    """The signature of a fragment image: every pixel of its face ``inset_mm`` inside the edge.

    Parameters
    ----------
    rgba : (H, W, 4) uint8
        8-bit sRGB colour with alpha (255 inside the fragment), as RePAIR's images and
        :func:`common.synth.realistic.fragment_rgba`.
    pixel_mm : float
        Pixel size, mm.
    inset_mm : float
        The damaged rim left out (the soft alpha edge and crumbled plaster).

    Returns
    -------
    FrescoSignature
    """
    rgba = np.asarray(rgba)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise ValueError(f"rgba must be an (H, W, 4) image, got shape {rgba.shape}")
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be positive, got {pixel_mm}")
    inner = _inner(rgba[..., 3], pixel_mm, inset_mm)
    if inner.sum() < 3:
        raise ValueError("the fragment has fewer than 3 pixels inside its rim")
    sig = lab_signature(_lab_from_srgb8(rgba[..., :3][inner]))
    x = rgba[..., :3][rgba[..., 3] >= 255].astype(np.float64) / 255.0
    lin = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    sig.face_lab = _lab_from_linear(lin.mean(axis=0))
    return sig


def _inner(alpha: np.ndarray, pixel_mm: float, inset_mm: float) -> np.ndarray:
    mask = (alpha >= 255).astype(np.uint8)
    r = int(round(inset_mm / pixel_mm))
    if r > 0:
        mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return mask.astype(bool)


def profile_signature(profile: np.ndarray, names=None, *, face_rgb=None) -> FrescoSignature:
    """The signature from a boundary profile (:func:`common.features.boundary.boundary_profile`).

    The matcher's index keeps each fragment's profile (√albedo at 0.8 and 1.6 mm inside the outline,
    every mm), so the signature needs no new feature: the colour of a band along the whole outline.
    It sees the plaster and the paint that reach the edge, less than the whole face shows.

    Parameters
    ----------
    profile : (K, C) array
        Boundary profile; its ``sqrt_{r,g,b}@{depth}`` columns (√ of linear RGB albedo) are used.
    names : list of str, optional
        Column names (default :func:`~common.features.boundary.boundary_channel_names`).
    face_rgb : (3,) array, optional
        Mean linear RGB albedo of the whole face (the features stage's ``colour_mean_{r,g,b}``,
        §5.4.1), kept as the signature's ``face_lab``.

    Returns
    -------
    FrescoSignature
    """
    from common.features.boundary import boundary_channel_names

    prof = np.asarray(profile, np.float32)
    names = list(boundary_channel_names() if names is None else names)
    if prof.ndim != 2 or prof.shape[1] != len(names):
        raise ValueError(f"profile must be a (K, {len(names)}) array matching names, got shape {prof.shape}")
    depths = sorted({n.split("@")[1] for n in names if n.startswith("sqrt_r@")})
    if not depths:
        raise ValueError("profile has no sqrt_r@<depth> column: no colour")
    rgb = np.concatenate([prof[:, [names.index(f"sqrt_{c}@{d}") for c in "rgb"]] for d in depths])
    rgb = rgb[np.all(np.isfinite(rgb), axis=1)]
    sig = lab_signature(_lab_from_linear(np.square(rgb)))
    if face_rgb is not None and np.all(np.isfinite(face_rgb)):
        sig.face_lab = _lab_from_linear(np.asarray(face_rgb, float))
    return sig


def grain_energies(rgba: np.ndarray, pixel_mm: float, scales_mm=(0.5, 1.0, 2.0, 4.0), *,
                   inset_mm: float = 1.0) -> np.ndarray:
    """Texture of a fragment's face: RMS lightness (L*) of difference-of-Gaussians bands.

    Band ``k`` is ``G(s_k) − G(2 s_k)`` of L*, normalised by the blurred coverage (so the edge adds
    nothing), its RMS over pixels whose band support lies inside the face (a Laplacian-pyramid
    energy, Burt & Adelson 1983).

    Parameters
    ----------
    rgba : (H, W, 4) uint8
    pixel_mm : float
    scales_mm : sequence of float
        Inner scale (Gaussian σ, mm) of each band.
    inset_mm : float
        Rim left out.

    Returns
    -------
    (len(scales_mm),) float
        L* units; NaN for a band whose support fits nowhere inside the face.
    """
    rgba = np.asarray(rgba)
    inner = _inner(rgba[..., 3], pixel_mm, inset_mm).astype(np.float32)
    L = _lab_from_srgb8(rgba[..., :3])[..., 0].astype(np.float32)
    out = []
    for s in scales_mm:
        bands = []
        for sig in (s / pixel_mm, 2 * s / pixel_mm):
            num = cv2.GaussianBlur(L * inner, (0, 0), sig)
            den = cv2.GaussianBlur(inner, (0, 0), sig)
            bands.append(num / np.maximum(den, 1e-6))
        r = int(np.ceil(4 * s / pixel_mm))
        core = cv2.erode(inner.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0
        v = (bands[0] - bands[1])[core]
        out.append(float(np.sqrt(np.mean(v * v))) if v.size >= 20 else float("nan"))
    return np.asarray(out)


def palette_distance(a: FrescoSignature, b: FrescoSignature) -> float:
    """Symmetric share-weighted distance (ΔE*ab) from each palette colour to the other's nearest.

    NaN when either fragment shows no paint; capped at :data:`PALETTE_CEILING_DE`.
    """
    if len(a.palette_lab) == 0 or len(b.palette_lab) == 0:
        return float("nan")
    d = np.linalg.norm(a.palette_lab[:, None, :] - b.palette_lab[None, :, :], axis=2)
    d = np.minimum(d, PALETTE_CEILING_DE)
    return 0.5 * float(a.palette_share @ d.min(axis=1) + b.palette_share @ d.min(axis=0))


def pair_features(a: FrescoSignature, b: FrescoSignature, features=PAIR_FEATURES) -> np.ndarray:
    """The differences of two signatures (``features``, default all of :data:`PAIR_FEATURES`, in order).

    The Bhattacharyya distance of their a*b* histograms (:func:`chroma_distance`), ``|ΔL*|`` and
    ``|Δa*b*|`` of the plaster, ``|Δ spread|``, ``|ΔL*|`` and ``|Δa*b*|`` of the face's
    mean colour (0 where either is unknown), the palette distance (0 where either shows no paint) and
    whether both show paint (0/1). Only the features asked for are computed (the ratio uses one).
    """
    def face():
        return np.nan_to_num(a.face_lab - b.face_lab, nan=0.0)

    def palette():
        pal = palette_distance(a, b)
        return pal if np.isfinite(pal) else 0.0

    rules = {"chroma_bhattacharyya": lambda: chroma_distance(a, b),
             "d_plaster_L": lambda: abs(a.plaster_lab[0] - b.plaster_lab[0]),
             "d_plaster_ab": lambda: float(np.hypot(*(a.plaster_lab[1:] - b.plaster_lab[1:]))),
             "d_spread_L": lambda: abs(a.plaster_spread_l - b.plaster_spread_l),
             "d_face_L": lambda: abs(face()[0]),
             "d_face_ab": lambda: float(np.hypot(*face()[1:])),
             "palette_de": palette,
             "both_painted": lambda: float(np.isfinite(palette_distance(a, b)))}
    unknown = [f for f in features if f not in rules]
    if unknown:
        raise ValueError(f"unknown pair features {unknown}; known: {', '.join(PAIR_FEATURES)}")
    return np.array([float(rules[f]()) for f in features])


def _pairs(groups, collections=None):
    g = np.asarray(groups)
    i, j = np.triu_indices(len(g), 1)
    if collections is not None:   # only pairs that meet in one collection
        c = np.asarray(collections)
        keep = c[i] == c[j]
        i, j = i[keep], j[keep]
    return i, j, (g[i] == g[j]).astype(int)


def fit_fresco_llr(signatures, groups, *, collections=None, features=LLR_FEATURES, C: float = 1.0,
                   clip: float = 4.0) -> dict:
    """Fit the same-fresco log-likelihood ratio on fragments of known frescoes.

    A logistic regression (L2, ``C``) of *same fresco* on the standardised :func:`pair_features`
    of every pair of fragments; its logit less the prior log odds of the training pairs is a
    log-likelihood ratio ``log p(x | same) / p(x | different)`` (Brümmer & du Preez 2006, §4).
    A difference whose fitted weight comes out positive (a larger difference would make one fresco
    *more* likely: noise of the training walls) is left out and the rest refitted.

    Parameters
    ----------
    signatures : sequence of FrescoSignature
    groups : sequence
        The fresco (wall) of each fragment; at least two frescoes, each with two fragments.
    collections : sequence, optional
        The collection of each fragment: only pairs within one collection are used (several pooled
        collections, each of walls that share a house's plaster, as a station's collection would).
    features : sequence of str
        The :data:`PAIR_FEATURES` used.
    C : float
        Inverse regularisation strength.
    clip : float
        The ratio is clipped to ``[-clip, clip]`` (nats): no single cue decides alone.

    Returns
    -------
    dict
        ``features``, ``mean``, ``scale``, ``coef`` (lists, one per feature used), ``intercept``
        (prior-free), ``clip``, ``n_same``, ``n_different``.
    """
    from sklearn.linear_model import LogisticRegression

    sigs = list(signatures)
    if len(sigs) != len(groups):
        raise ValueError(f"{len(sigs)} signatures but {len(groups)} groups")
    i, j, y = _pairs(groups, collections)
    if y.sum() == 0 or (1 - y).sum() == 0:
        raise ValueError("fitting needs pairs of one fresco and pairs of different frescoes")
    cols = [PAIR_FEATURES.index(f) for f in features]
    x = np.array([pair_features(sigs[a], sigs[b]) for a, b in zip(i, j)])[:, cols]
    mean, scale = x.mean(axis=0), x.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    z = (x - mean) / scale
    use = np.ones(x.shape[1], bool)
    while True:
        lr = LogisticRegression(C=C, max_iter=1000).fit(z[:, use], y)
        coef = np.zeros(x.shape[1])
        coef[use] = lr.coef_[0]
        wrong = [k for k, c in enumerate(cols) if c in _DIFFERENCES and use[k] and coef[k] > 0]
        if not wrong:
            break
        use[max(wrong, key=lambda k: coef[k])] = False
    prior = np.log(y.mean() / (1 - y.mean()))
    return dict(features=list(features), mean=mean.tolist(), scale=scale.tolist(), coef=coef.tolist(),
                intercept=float(lr.intercept_[0] - prior), clip=float(clip), n_same=int(y.sum()),
                n_different=int((1 - y).sum()))


def fresco_llr(a: FrescoSignature, b: FrescoSignature, params: dict | None = None) -> float:
    """Log-likelihood ratio (nats) that two fragments come from the same fresco rather than two.

    Parameters
    ----------
    a, b : FrescoSignature
    params : dict, optional
        From :func:`fit_fresco_llr` (default :data:`FRESCO_LLR`).
    """
    p = FRESCO_LLR if params is None else params
    if p is None:
        raise ValueError("no fitted same-fresco parameters (FRESCO_LLR is None): run fit_fresco_llr")
    x = (pair_features(a, b, p["features"]) - np.asarray(p["mean"])) / np.asarray(p["scale"])
    return float(np.clip(x @ np.asarray(p["coef"]) + p["intercept"], -p["clip"], p["clip"]))


def with_fresco(probability, llr, weight: float = 1.0) -> np.ndarray:
    """Join probabilities with the same-fresco log-likelihood ratio added to their logit (naive Bayes).

    ``weight`` 1 treats the ratio as independent evidence; NaN ratios leave the probability as it is.
    """
    p = np.clip(np.asarray(probability, float), 1e-12, 1 - 1e-12)
    r = np.asarray(llr, float)
    lp = np.log(p) - np.log1p(-p) + weight * np.nan_to_num(r, nan=0.0)
    return 1.0 / (1.0 + np.exp(-lp))
