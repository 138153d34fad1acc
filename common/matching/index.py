"""Staged matching that scales (thesis §5.2.1): prune with per-fragment cues, rank with per-patch
cues, check the best few with the per-match alignment.

Stage 1 — **prune** without an n² pass. Each fragment is a point in the space of its fragment-level
descriptors, scaled per column by the model's weight ``max(0, −w_k) / s_k``, so the L1 distance
between two points is exactly how much the fragment-level correspondences lower the model's logit.
A KD-tree (scipy ``cKDTree``, Minkowski p = 1) over those points returns a new fragment's
``n_candidates`` nearest fragments in O(log n). Where the new fragment has a boundary profile (and the
same-fresco ratio is on), the candidates are instead the ``n_candidates`` likeliest of its fresco by their
boundary colours (one matrix product over every fragment's a*b* histogram): on realistic collections
that keeps far more true partners than the fragment cues (docs/matching.md, "What reaches the ribbon").

Stage 2 — **rank** the candidates: every patch pair between the new fragment and all candidates is
scored in one vectorised batch (:func:`common.matching.pairs.pair_rows` semantics); a fragment
pair's *patch probability* is the mean of its ``top_m`` best patch-pair probabilities (a true join
has several matching patch pairs along the shared break; a single chance coincidence does not make
one). Its ranking **probability** then removes the *hubness* of the two fragments: some fragments
(plain colour, straight cuts) look like a match to almost everything, so their best patch pairs are
high against every fragment and crowd true neighbours out of other fragments' lists. Each fragment's
hubness ``μ_f`` is the mean logit of its patch probability against its pruned candidates (kept
from its last proposal under the current model), and the pair logit becomes
``logit(p_ab) − ½(μ_a − μ̄) − ½(μ_b − μ̄)`` (``μ̄`` the median over the index, so the average
calibration stays), i.e. the mean-centred similarity used against hubs in high-dimensional
nearest-neighbour retrieval (Radovanović et al., JMLR 11, 2010; "CSLS", Conneau et al., ICLR 2018).
On the synthetic test wall it raises top-5 recall of true neighbours from 0.22 to 0.24 (docs/matching.md).

Stage 2½ — **ribbon**: the best ``RIBBON_CANDIDATES`` of stage 2 (by its logit with the same-fresco ratio
added, below: the patch classifier alone keeps too few true partners on real collections) are re-ranked by the colour
ribbon (:mod:`common.matching.ribbon`: do the paint and the plaster continue across the two
boundaries?), whose score the model's calibration turns into the join probability. The rarity of
the query's boundary colours is measured against a reference sample of the index's boundaries,
rebuilt whenever the index has grown or shrunk by a tenth. The patch
classifier decides which candidates get this far (and learns from verdicts); the ribbon decides
their order. On the synthetic test wall this raises top-5 recall of true neighbours from 0.25 to
about 0.5 (docs/matching.md). Fragments without a boundary profile (feature tables older than schema
version 2) or a model without a ribbon calibration keep the stage-2 ranking.

**Same fresco** — after stage 2½ each candidate's probability gains the log-likelihood ratio that
the two fragments come from one fresco (:mod:`common.matching.fresco`: their boundaries' plaster
and paint colours), so that in a collection of several frescoes the later stages, which judge the
crack alone, do not lift pieces of another fresco.

Stage 3 — **dock** the best ``DOCK_CANDIDATES`` per fragment (:mod:`common.matching.docking`:
gap-tolerant outline complementarity searched over every pose by FFT correlation, one search per
pair giving 30 candidate poses and 70 more to offer, the fragment's turned maps kept across its partners). The contact,
corrected for both fragments' docking hubness, is calibrated into the join probability; the earlier
stages' evidence and the paint continuing across the crack (:mod:`common.matching.paint`, its best
over the 30 candidate poses) are added to its logit. The proposed pose is the candidate of the 30 the learned
pose chooser scores best (contact, paint and the outlines' facing geometry:
:func:`common.matching.pose.learned_pose_scores`), and the next 19 of all 100 are offered beside it
(:func:`common.matching.pose.offered_poses`). A pair is docked once: its result is cached, and
kept in the proposal store where the index is given one (``MatchIndex(dockings=store)``, keyed by
:func:`docking_inputs` and :func:`docking_version`), so other indexes over that store — other matcher
workers, a restarted one — read it instead of docking it again. Candidates that stage 3 does not dock
keep their order below the docked ones; without a docking calibration the best ``check`` are aligned by
:func:`common.matching.alignment.align_fragments` instead.

**Mutual proximity** — every fragment's last full ranking is kept (:attr:`MatchIndex.rankings`), and
a pair's standing in both fragments' rankings is one symmetric score
(:func:`common.matching.mutual.mutual_proximity`; :meth:`MatchIndex.mutual`): a probability is
calibrated against its own query's other candidates, so the station orders a fragment's proposals,
which come from several queries, by it. :meth:`MatchIndex.rank_again` brings a fragment's ranking up
to date after new fragments arrived, and :meth:`MatchIndex.rank_all` every fragment's after a model
update (with the dockings made before; the pairs new to a fragment's docked best are returned, to be
docked as jobs of their own). Measured figures of every stage: docs/matching.md.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from common.features.boundary import boundary_channel_names
from common.matching.alignment import Alignment, align_fragments
from collections import OrderedDict

from common.matching.docking import (DOCK_HUB_TOP, Docking, DockingFrame, dock_frames, docking_contact_mm,
                                     hub_corrected, invert_docking, paint_from_profile)
from common.matching.models import MatchModel
from common.matching.pairs import FragmentCues, _columnwise, _descs, column_rules, strip_gap
from common.matching.ribbon import (RIBBON_WINDOW_MM, prepare_ribbon, ribbon_population, ribbon_probability,
                                    ribbon_scores, sample_rarity)
from common.threads import one_blas_thread


#: a query's hubness is (re)estimated only from at least this many scored candidates
HUBNESS_MIN_OTHERS = 20
#: stage 2 passes this many candidates per fragment to the ribbon (stage 2½)
RIBBON_CANDIDATES = 50
#: stage 2½ passes this many candidates per fragment to the gap-tolerant docking (stage 3)
DOCK_CANDIDATES = 12
#: stage 3 adds the earlier stages' relative evidence to the docking's (see _rank_by_docking)
DOCK_KEEPS_EARLIER_EVIDENCE = True
#: stage 3 adds the pair's paint continuity (best over the docking's candidate poses) to the join's
#: logit (:func:`common.matching.paint.with_paint`), where both fragments have a boundary profile
DOCK_USES_PAINT = True
#: with paint, a pair's one docking keeps this many candidate poses (this many per rotation): its best is the
#: pair's geometric evidence and the paint continuity is the best over all of them (paint.paint_pair_mm)
DOCK_PAINT_POSES, DOCK_PAINT_PER_ANGLE = 30, 3
#: the same search also gives this many further candidates (docking.dock_frames' more_poses, up to 10 local maxima
#: per rotation). The pair's proposed pose is the learned chooser's best of the first DOCK_PAINT_POSES, and the
#: next pose.ALTERNATIVE_POSES of all are offered beside it (pose.offered_poses). They widen what is offered,
#: not the evidence or the choice: the paint's best over 100 candidates finds paint by chance for more wrong
#: pairs, and the chooser was fitted on the 30 (docs/matching.md, "More candidate poses to offer")
DOCK_MORE_POSES = 70
#: docking frames (docking.DockingFrame: a fragment's maps and spectra at every rotation, which serve all
#: its partners) are kept for the most recently docked fragments, within this many MB
DOCK_FRAMES_MB = 512
#: version of what a pair's docking gives (MatchIndex._dock_pair: docking.py's search, paint.py's continuity,
#: pose.py's choice and alternatives): bump it when any of them changes its numbers, so that dockings kept in
#: the proposal store by an earlier version are docked again (docking_version adds the settings above)
DOCKING_VERSION = "docking-2"


def docking_version() -> str:
    """The version of a pair's docking as :class:`MatchIndex` makes it now: :data:`DOCKING_VERSION` with the
    settings that change its numbers (the candidate poses kept, whether paint is used, the alternatives
    offered), e.g. ``"docking-2/poses-30x3+70/paint/alternatives-19"``."""
    from common.matching.pose import ALTERNATIVE_POSES

    return (f"{DOCKING_VERSION}/poses-{DOCK_PAINT_POSES}x{DOCK_PAINT_PER_ANGLE}+{DOCK_MORE_POSES}"
            f"/{'paint' if DOCK_USES_PAINT else 'no-paint'}/alternatives-{ALTERNATIVE_POSES}")


def docking_inputs(contour_mm: np.ndarray | None, boundary_profile: np.ndarray | None = None) -> str | None:
    """Digest of what a fragment gives its dockings (:meth:`MatchIndex._dock_pair`): its outline and, where it
    has one, its boundary profile (the paint), as stored dockings are keyed (docs/storage.md).

    sha256 (hex) of ``b"contour_mm <rows> <cols>\n"`` and the outline as little-endian float64 in row order,
    then, with a profile, ``b"profile <rows> <cols>\n"`` and the profile as little-endian float32. None
    without an outline (such a fragment is never docked).
    """
    import hashlib

    if contour_mm is None:
        return None
    h = hashlib.sha256()
    for name, a, dtype in (("contour_mm", contour_mm, "<f8"), ("profile", boundary_profile, "<f4")):
        if a is not None:
            a = np.ascontiguousarray(a, dtype=dtype)
            h.update(f"{name} {' '.join(map(str, a.shape))}\n".encode())
            h.update(a.tobytes())
    return h.hexdigest()


@dataclass
class Candidate:
    """A scored fragment pair from the index: ``fragment`` (the query) against ``other``."""

    fragment: str
    other: str
    probability: float
    patch_a: int            # best patch of the query (row in its FragmentCues)
    patch_b: int            # best patch of the other fragment
    top_pairs: np.ndarray   # (m, 2) the top_m patch pairs (query patch, other patch)
    evidence: np.ndarray    # (m, D) their correspondence rows
    alignment: Alignment | None = None
    patch_probability: float = float("nan")  # mean of the top_m patch-pair probabilities (before hubness)
    ribbon_score: float = float("nan")       # colour-ribbon score (stage 2½), NaN when not computed
    ribbon_arc_mm: tuple | None = None       # (arc on the query, arc on the other) of the ribbon's best run
    docking: Docking | None = None           # stage 3: the other fragment docked against the query
    docking_contact_mm: float = float("nan")  # its shared-crack length less the two hubnesses (mm)
    paint_mm: float = float("nan")           # stage 3: paint continuing across the crack (mm, paint.py)
    fresco_llr: float = float("nan")         # same-fresco log-likelihood ratio (fresco.py), NaN when not computed
    patch_logit: float = float("nan")        # stage 2: logit of the hubness-corrected probability
    mutual: float = float("nan")             # mutual proximity of the pair (MatchIndex.mutual), set by propose


class MatchIndex:
    """In-memory index of fragments' matching cues, grown one fragment at a time.

    It is a cache: everything in it is rebuilt from the feature artifacts that the proposal store
    lists, so a matcher worker can be killed at any time.

    Parameters
    ----------
    use_hubness : bool
        Rank by the hubness-corrected probability (False: the patch probability, as before).
    dockings : common.matching.proposals.ProposalStore, optional
        Where pairs' dockings are kept beyond this index (its ``docking`` and ``put_docking``): a pair is
        read from it before it is docked, and a new docking is written to it, keyed by both fragments'
        :func:`docking_inputs` and :func:`docking_version`; so an index over the same store — another
        worker's, or a restarted one's — docks none of the pairs this one docked. None: in memory only.
    single_fresco : bool
        The collection is the pieces of one fresco: the same-fresco ratio, which tells frescoes apart, does not
        re-order the ribbon's candidates (:meth:`_rank_by_fresco`); stage 1 and the ribbon's cut still choose by
        the boundary colours. Among the pieces of one fresco of plain plaster with sparse paint the ratio only
        rewards look-alikes: one synthetic Pompeian wall of 240 pieces, pooled top-5 0.186 with it, 0.226 without;
        0.285 and 0.333 among 50 (docs/matching.md, "A ribbon at three lengths, and one fresco"). On a figure
        painting, whose boundary colours say which part of the picture a piece is from, it helps: DAFNE 0.438 with
        it, 0.385 without ("One fresco richly painted").
    fresco_weight : float, optional
        The same-fresco ratio's weight in the ranking (stage 1's choice, the ribbon's cut and after stage 2½);
        None: :data:`common.matching.fresco.FRESCO_WEIGHT` (8, best for collections of several frescoes). A
        collection of one figure painting ranks best at 4 (docs/matching.md, "The same-fresco ratio's weight
        above 4"); 0 turns the ratio off everywhere.
    """

    def __init__(self, *, use_hubness: bool = True, dockings=None, single_fresco: bool = False,
                 fresco_weight: float | None = None):
        #: rank by the hubness-corrected probability (False: the patch probability, as before)
        self.use_hubness = bool(use_hubness)
        #: the collection is one fresco: the same-fresco ratio does not re-order the ribbon's candidates
        self.single_fresco = bool(single_fresco)
        if fresco_weight is not None and not (np.isfinite(fresco_weight) and fresco_weight >= 0):
            raise ValueError(f"fresco_weight must be a number >= 0, got {fresco_weight!r}")
        #: the same-fresco ratio's weight; None: fresco.FRESCO_WEIGHT (read when ranking)
        self.fresco_weight = None if fresco_weight is None else float(fresco_weight)
        #: the store of dockings shared with other indexes (the proposal store), or None
        self.docking_store = dockings
        #: fragment → digest of its docking inputs (docking_inputs: outline and boundary profile)
        self._inputs: dict[str, str | None] = {}
        self.cues: dict[str, FragmentCues] = {}
        self._order: list[str] = []
        #: stage 1 by fresco (_chroma_rows): fragments with a signature, their rows, and those to look at again
        self._chroma_names: list[str] = []
        self._chroma_pos: dict[str, int] = {}
        self._chroma_matrix = np.zeros((0, 0), np.float32)
        self._chroma_stale: set[str] = set()
        self._dirty = True
        self._tree = None
        self._tree_n = 0
        self._tree_weights = None
        self.contours: dict[str, np.ndarray] = {}
        #: fragment → its boundary profile prepared for the ribbon (features schema ≥ 2)
        self.profiles: dict = {}
        self._population = None     # rarity reference (ribbon.py), rebuilt as the index grows
        self._population_n = 0
        #: fragment → (model version, hubness μ: mean logit against its candidates)
        self.hubness: dict[str, tuple[str, float]] = {}
        #: docking results by unordered pair (model-independent, so kept across model updates)
        self._dockings: dict[tuple[str, str], Docking] = {}
        #: fragment → docking hubness (mean contact of its best dockings, mm); kept in :attr:`docking_store`
        #: too, so every worker corrects a pair by the same values (:meth:`_recall_dock_hubness`)
        self.dock_hubness: dict[str, float] = {}
        self._dock_hubness_recalled = False
        #: fragment → paint along its outline as deviations from its plaster (for the docking)
        self.paint: dict[str, np.ndarray] = {}
        #: fragment → boundary profile as given (for its paint field, built when first needed)
        self._raw_profiles: dict[str, np.ndarray] = {}
        self._paint_fields: dict = {}
        #: paint continuity by unordered pair, mm (model-independent, like the dockings)
        self._paint_pairs: dict[tuple[str, str], float] = {}
        #: pose by unordered pair where the learned chooser chose it among the docking's candidates
        #: (pose.learned_pose_scores over contact, paint and facing geometry)
        self._poses: dict[tuple[str, str], Docking] = {}
        #: the pair's next-best distinct candidates of all 100 (pose.offered_poses), offered beside its pose
        self._alternatives: dict[tuple[str, str], list[Docking]] = {}
        #: fragment → its docking frame, least recently used first (bounded by DOCK_FRAMES_MB)
        self._frames: OrderedDict[str, DockingFrame] = OrderedDict()
        #: fragment → its candidates best first, from its last full ranking (propose, rank_again)
        self.rankings: dict[str, list[str]] = {}

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, fragment: str) -> bool:
        return fragment in self.cues

    def add(self, cues: FragmentCues, contour_mm: np.ndarray | None = None,
            boundary_profile: np.ndarray | None = None) -> None:
        """Add (or replace) a fragment, with its contour (stage 3) and boundary profile (stage 2½).

        A new fragment is appended to the stacked arrays (amortised O(its own patches): buffers
        grow by doubling), so adding one to a large index does not copy the others; replacing a
        fragment marks the index for a full rebuild.
        """
        if contour_mm is not None:
            self.contours[cues.fragment] = np.asarray(contour_mm, float)
            self._frames.pop(cues.fragment, None)
        self._chroma_stale.add(cues.fragment)
        self.profiles.pop(cues.fragment, None)
        self.paint.pop(cues.fragment, None)
        self._raw_profiles.pop(cues.fragment, None)
        self._paint_fields.pop(cues.fragment, None)
        if boundary_profile is not None:
            p = np.asarray(boundary_profile, np.float32)
            names = boundary_channel_names()
            if p.ndim == 2 and len(p) >= 3 and p.shape[1] == len(names):
                self.profiles[cues.fragment] = prepare_ribbon(p, names)
                self._raw_profiles[cues.fragment] = p
                # the profile runs from the contour's first point in its order, as contour_mm does
                self.paint[cues.fragment] = paint_from_profile(p)
        inputs = docking_inputs(self.contours.get(cues.fragment), self._raw_profiles.get(cues.fragment))
        if cues.fragment in self.cues:
            self.cues[cues.fragment] = cues
            self.hubness.pop(cues.fragment, None)
            self.rankings.pop(cues.fragment, None)
            if inputs != self._inputs.get(cues.fragment):
                self._forget_dockings(cues.fragment)
            self._inputs[cues.fragment] = inputs
            self._dirty = True
            return
        self._order.append(cues.fragment)
        self.cues[cues.fragment] = cues
        self._inputs[cues.fragment] = inputs
        if not self._dirty:
            self._append(cues)   # the KD-tree stays; the new fragment is in its tail

    def remove(self, fragment: str) -> None:
        """Forget a fragment (full rebuild on next use)."""
        if fragment not in self.cues:
            return
        last = self._order[-1] == fragment
        in_tail = last and len(self._order) - 1 >= self._tree_n
        self._chroma_stale.add(fragment)
        self._order.remove(fragment)
        del self.cues[fragment]
        self.contours.pop(fragment, None)
        self.profiles.pop(fragment, None)
        self.paint.pop(fragment, None)
        self._raw_profiles.pop(fragment, None)
        self._paint_fields.pop(fragment, None)
        self.hubness.pop(fragment, None)
        self.rankings.pop(fragment, None)
        self._forget_dockings(fragment)
        self._inputs.pop(fragment, None)
        if not in_tail:
            self._tree = None
        if last and not self._dirty:  # undo the last append without a rebuild
            self._n -= 1
            self._offsets_list.pop()
            self._offsets = np.asarray(self._offsets_list)
        else:
            self._dirty = True

    # -- stacked arrays ----------------------------------------------------------------------
    def _build(self):
        fd, pd = _descs()
        cs = [self.cues[f] for f in self._order]
        n_strips = len(cs[0].strips) if cs else 0
        widths = [cs[0].strips[m].shape[1] for m in range(n_strips)] if cs else []
        cap_f = max(16, 2 * len(cs))
        cap_p = max(256, 2 * sum(len(c) for c in cs))
        self._vbuf = np.empty((cap_f, len(fd)))
        self._pbuf = np.empty((cap_p, len(pd)))
        self._sbuf = [np.empty((cap_p, w, 2)) for w in widths]
        self._gbuf = [np.empty((cap_p, 2 * w + 1), np.float32) for w in widths]   # _strip_b_rows
        self._n = 0
        self._offsets_list = [0]
        self._dirty = False
        self._tree = None
        for c in cs:
            self._append(c)

    def _append(self, c: FragmentCues):
        if not self._sbuf and c.strips:  # the index was built empty: size the strip buffers now
            self._sbuf = [np.empty((len(self._pbuf), s.shape[1], 2)) for s in c.strips]
            self._gbuf = [np.empty((len(self._pbuf), 2 * s.shape[1] + 1), np.float32) for s in c.strips]
        n, npch = self._n, self._offsets_list[-1]
        if n + 1 > len(self._vbuf):
            self._vbuf = np.concatenate([self._vbuf, np.empty_like(self._vbuf)])
        while npch + len(c) > len(self._pbuf):
            self._pbuf = np.concatenate([self._pbuf, np.empty_like(self._pbuf)])
            self._sbuf = [np.concatenate([b, np.empty_like(b)]) for b in self._sbuf]
            self._gbuf = [np.concatenate([b, np.empty_like(b)]) for b in self._gbuf]
        self._vbuf[n] = c.values
        self._pbuf[npch:npch + len(c)] = c.patches
        for m, b in enumerate(self._sbuf):
            b[npch:npch + len(c)] = c.strips[m]
            self._gbuf[m][npch:npch + len(c)] = _strip_b_rows(c.strips[m])
        self._n += 1
        self._offsets_list.append(npch + len(c))
        self._offsets = np.asarray(self._offsets_list)

    @property
    def _values(self):
        return self._vbuf[:self._n]

    @property
    def _patches(self):
        return self._pbuf[:self._offsets_list[-1]]

    @property
    def _strips(self):
        return [b[:self._offsets_list[-1]] for b in self._sbuf]

    @property
    def _strip_rows(self):
        return [b[:self._offsets_list[-1]] for b in self._gbuf]

    def _ensure(self):
        if self._dirty:
            self._build()

    def _prune_space(self, model: MatchModel):
        fd, _ = _descs()
        w = np.array([max(0.0, -model.coef[model.columns.index(d.key)]) / model.scale[model.columns.index(d.key)]
                      if d.key in model.columns else 0.0 for d in fd])
        v = self._values
        with warnings.catch_warnings():   # a cue missing everywhere (colour-only collections) is expected
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(v, axis=0) if len(v) else np.zeros(v.shape[1])
        med = np.where(np.isfinite(med), med, 0.0)
        return w, med

    def _point(self, values, w, med):
        return np.where(np.isfinite(values), values, med) * w

    def candidates(self, cues: FragmentCues, model: MatchModel, n_candidates: int = 100) -> list[str]:
        """Stage 1: the ``n_candidates`` likeliest of the query's fresco (:meth:`_candidates_by_fresco`), or, for a
        query without a boundary profile, those nearest in the weighted per-fragment space.

        The KD-tree covers the fragments present when it was built; fragments appended since (the
        *tail*) are compared directly, and the tree is rebuilt once the tail exceeds 5 % of the
        index, so a stream of new fragments costs O(log n) each, amortised.
        """
        self._ensure()
        others = [f for f in self._order if f != cues.fragment]
        if len(others) <= n_candidates:
            return others
        by_fresco = self._candidates_by_fresco(cues.fragment, n_candidates)
        if by_fresco is not None:
            return by_fresco
        n = len(self._order)
        if (self._tree is None or self._tree_weights != model.version
                or n - self._tree_n > max(32, n // 20)):
            w, med = self._prune_space(model)
            self._tree = cKDTree(self._point(self._values, w, med))
            self._tree_med, self._tree_w = med, w
            self._tree_weights = model.version
            self._tree_n = n
        q = self._point(cues.values, self._tree_w, self._tree_med)
        k = min(n_candidates + 1, self._tree_n)
        d, idx = self._tree.query(q, k=k, p=1)
        d, idx = np.atleast_1d(d), np.atleast_1d(idx)
        if n > self._tree_n:
            tail = np.arange(self._tree_n, n)
            dt = np.abs(self._point(self._values[tail], self._tree_w, self._tree_med) - q).sum(axis=1)
            d, idx = np.concatenate([d, dt]), np.concatenate([idx, tail])
        order = idx[np.argsort(d, kind="stable")]
        out = [self._order[i] for i in order if i < n]
        return [f for f in out if f != cues.fragment][:n_candidates]

    def _candidates_by_fresco(self, fragment: str, n_candidates: int) -> list[str] | None:
        """Stage 1 by which fresco a piece comes from: the ``n_candidates`` fragments whose boundary colours are
        likeliest the query's fresco (highest Bhattacharyya coefficient of the two a*b* histograms, the one cue of
        the same-fresco ratio, :func:`common.matching.fresco.fresco_llr`: the same order), one matrix product.

        On realistic collections the weighted fragment cues of the KD-tree keep too few true partners: pooled with
        384 factory pieces, 60 % of RePAIR's true links (58 % of the factory's) were among a fragment's 100 nearest,
        against 95 % (79 %) by the ratio (docs/matching.md, "What reaches the ribbon"). None when the query has no
        signature (no boundary profile) or the ratio is off: the KD-tree decides. Fragments without a signature
        are reached only through the KD-tree of such queries."""
        sig = self._ratio_signature(fragment)
        if sig is None:
            return None
        names, rows = self._chroma_rows()
        with one_blas_thread():   # a BLAS thread pool would spin beside the other workers for one product
            bc = rows @ np.sqrt(sig.chroma_hist, dtype=np.float32).ravel()
        # ties (copies, identical colours) by name, so any index with these fragments gives the same list
        out = [names[i] for i in np.lexsort((np.array(names), -bc)) if names[i] != fragment]
        return out[:n_candidates]

    def _chroma_rows(self) -> tuple[list[str], np.ndarray]:
        """The fragments with a fresco signature and their √ a*b* histograms as rows (float32). Kept up to date
        one fragment at a time (:meth:`add` and :meth:`remove` mark it; a removed row is replaced by the last),
        so a new fragment in a large index costs one row, not a copy of all (12 ms at n = 2,000)."""
        names, pos = self._chroma_names, self._chroma_pos
        for f in sorted(self._chroma_stale):
            sig = self._fresco_signature(f) if f in self.cues else None
            i = pos.get(f)
            if sig is None:
                if i is not None:   # the last row takes its place
                    last = names.pop()
                    del pos[f]
                    if last != f:
                        self._chroma_matrix[i] = self._chroma_matrix[len(names)]
                        names[i], pos[last] = last, i
                continue
            row = np.sqrt(sig.chroma_hist, dtype=np.float32).ravel()
            if i is None:
                if self._chroma_matrix.shape[1] != row.size or len(names) == len(self._chroma_matrix):
                    grown = np.zeros((max(64, 2 * len(self._chroma_matrix)), row.size), np.float32)
                    if self._chroma_matrix.shape[1] == row.size:
                        grown[:len(names)] = self._chroma_matrix[:len(names)]
                    self._chroma_matrix = grown
                i = pos[f] = len(names)
                names.append(f)
            self._chroma_matrix[i] = row
        self._chroma_stale.clear()
        return names, self._chroma_matrix[:len(names)]

    def score(self, cues: FragmentCues, others: list[str], model: MatchModel, *,
              chunk_rows: int = 100_000, evidence_for: int | None = None,
              update_hubness: bool = True) -> list[Candidate]:
        """Stage 2: probability of each (query, other) pair from all their patch pairs, best first.

        ``evidence_for``: attach the evidence rows to the best this many only (None: all).
        ``update_hubness``: take the query's hubness from this list when it is long enough (False
        for a list that is not a fair sample of its candidates, e.g. only the kept ones).
        """
        # many small matrix products: BLAS threads only add overhead (and fight the other workers)
        with one_blas_thread():
            return self._score(cues, others, model, chunk_rows, evidence_for, update_hubness)

    def _score(self, cues, others, model, chunk_rows, evidence_for, update_hubness):
        self._ensure()
        if len(cues) == 0 or not others:
            return []
        fd, pd = _descs()
        pos = {f: i for i, f in enumerate(self._order)}
        idx = [pos[o] for o in others if o in pos and o != cues.fragment]
        starts, stops = self._offsets[idx], self._offsets[np.array(idx) + 1]
        rows_b = np.concatenate([np.arange(s, e) for s, e in zip(starts, stops)]) if idx else np.zeros(0, int)
        owner = np.repeat(np.arange(len(idx)), stops - starts)
        n_a, n_b = len(cues), len(rows_b)
        # fragment-level correspondences of the query against each candidate
        fcol = _columnwise(fd, cues.values[None, :], self._values[idx])
        probs = np.empty((n_a, n_b), np.float32)
        per_chunk = max(1, chunk_rows // max(n_a, 1))
        nf, npd = len(fd), len(pd)
        # the logistic model is linear in the correspondences: its logit is added up column by
        # column over the (query patch × candidate patch) grid, never building the rows (which
        # at real sizes, ~80 × 8,000 patch pairs × 65 columns, cost 4× more)
        w, constant = model.linear()
        logit_f = np.where(np.isnan(fcol), model.impute[:nf], fcol) @ w[:nf] + constant
        for c0 in range(0, n_b, per_chunk):
            rb = rows_b[c0:c0 + per_chunk]
            z = self._patch_logits(cues, rb, w[nf:], model.impute[nf:], pd)
            z += logit_f[owner[c0:c0 + per_chunk]][None, :].astype(np.float32)
            np.clip(z, -60, 60, out=z)
            np.negative(z, out=z)
            np.exp(z, out=z)
            z += 1.0
            np.reciprocal(z, out=probs[:, c0:c0 + len(rb)])
        m = model.top_m
        seg = np.concatenate([[0], np.cumsum(stops - starts)])
        found = []
        for k, o in enumerate(idx):
            block = probs[:, seg[k]:seg[k + 1]]
            if block.size == 0:
                continue
            flat = block.ravel()
            top = np.argpartition(-flat, min(m, flat.size) - 1)[:m] if flat.size > m else np.arange(flat.size)
            top = top[np.argsort(-flat[top])]
            found.append((float(flat[top].astype(float).mean()), k, o, np.unravel_index(top, block.shape)))
        # hubness (module docstring): the query's μ from this list when it is long enough to be a
        # fair sample, the others' from their own last proposal under this model
        raw = np.array([t[0] for t in found])
        logit = np.log(np.clip(raw, 1e-12, 1.0)) - np.log(np.clip(1.0 - raw, 1e-12, 1.0))
        if update_hubness and len(found) >= HUBNESS_MIN_OTHERS:
            self.hubness[cues.fragment] = (model.version, float(logit.mean()))
        mu = {f: v for f, (ver, v) in self.hubness.items() if ver == model.version}
        centre = float(np.median(list(mu.values()))) if mu else 0.0
        mu_q = mu.get(cues.fragment, centre)
        mu_o = np.array([mu.get(self._order[t[2]], centre) for t in found])
        corrected = (1.0 / (1.0 + np.exp(-(logit - 0.5 * (mu_q - centre) - 0.5 * (mu_o - centre))))
                     if self.use_hubness else raw)
        order = np.argsort(-corrected, kind="stable")
        out = []
        for rank, j in enumerate(order):
            p, k, o, (ia, ib) = found[j]
            # evidence rows (what a verdict will teach) only for the candidates that are kept
            ev = (self._rows(cues, ia, rows_b[seg[k] + ib], np.full(len(ib), k), fcol, nf, npd, pd)
                  if evidence_for is None or rank < evidence_for else None)
            out.append(Candidate(cues.fragment, self._order[o], float(corrected[j]), int(ia[0]), int(ib[0]),
                                 np.column_stack([ia, ib]), ev, patch_probability=p,
                                 patch_logit=float(np.log(max(corrected[j], 1e-12)) - np.log(max(1 - corrected[j], 1e-12)))))
        return out

    def refresh_hubness(self, fragments, model: MatchModel, *, n_candidates: int = 100) -> int:
        """Recompute the hubness of ``fragments`` whose value is missing or from another model
        (after a model update), each against its pruned candidates; returns how many were refreshed."""
        n = 0
        for f in fragments:
            if self.use_hubness and f in self.cues and self.hubness.get(f, ("", 0.0))[0] != model.version \
                    and len(self.cues[f]):
                self.score(self.cues[f], self.candidates(self.cues[f], model, n_candidates), model, evidence_for=0)
                n += 1
        return n

    def _patch_logits(self, cues, rows_b, w, impute, pd) -> np.ndarray:
        """The patch and strip columns' share of the logit, every query patch × ``rows_b``, (Na, Nb)
        float32.

        ``w``, ``impute``: the model's weights and imputed values of those columns (after the
        fragment-level ones), as :meth:`MatchModel.linear` and :meth:`MatchModel.decision` use them.
        Each column's term ``w·|a − b|`` is ``±|a·|w| − b·|w||`` (``b`` negated for ``abs_sum``
        columns, angles taken modulo their period first so one wrap suffices), added up in float32
        from contiguous per-column vectors: the grid is memory-bound, and float32 halves its traffic
        (the logits move by ~1e-6, far below any difference that orders candidates).
        """
        is_sum, is_angle, period = column_rules(pd)
        npd = len(pd)
        scale = np.abs(w[:npd])
        a_all, b_all = cues.patches.T, self._patches[rows_b].T          # (columns, patches)
        z = np.zeros((len(cues), len(rows_b)), np.float32)
        d = np.empty_like(z)
        constant = 0.0   # terms that are the same for every pair (a column missing on one side altogether)
        for k in np.flatnonzero(scale > 0):
            a, b = a_all[k], b_all[k]
            na, nb = np.isnan(a), np.isnan(b)
            imputed = scale[k] * impute[k]
            if na.all() or nb.all():
                constant += np.sign(w[k]) * imputed
                continue
            if is_angle[k]:
                a, b = np.mod(a, period[k]), np.mod(b, period[k])
            a = np.where(na, 0.0, a * scale[k]).astype(np.float32)
            b = np.where(nb, 0.0, (-b if is_sum[k] else b) * scale[k]).astype(np.float32)
            np.subtract(a[:, None], b[None, :], out=d)
            np.abs(d, out=d)
            if is_angle[k]:
                np.minimum(d, np.float32(period[k] * scale[k]) - d, out=d)
            if na.any():
                d[na] = imputed
            if nb.any():
                d[:, nb] = imputed
            (np.add if w[k] > 0 else np.subtract)(z, d, out=z)
        for m, s in enumerate(self._strip_rows):
            g = _strip_gap_all(cues.strips[m], s[rows_b], missing=impute[npd + m])
            g *= np.float32(w[npd + m])
            z += g
        if constant:
            z += np.float32(constant)
        return z

    def _evidence(self, cues: FragmentCues, candidate: Candidate) -> np.ndarray:
        """Correspondence rows of a stage-2 candidate's best patch pairs (its ``top_pairs``), as
        :meth:`score` attaches them: a patch pair's row does not depend on the other candidates."""
        fd, pd = _descs()
        o = self._order.index(candidate.other)
        ia, ib = candidate.top_pairs[:, 0], candidate.top_pairs[:, 1]
        fcol = _columnwise(fd, cues.values[None, :], self._values[[o]])
        return self._rows(cues, ia, self._offsets[o] + ib, np.zeros(len(ia), int), fcol, len(fd), len(pd), pd)

    def _rows(self, cues, ia, rows_b, owner, fcol, nf, npd, pd):
        """Correspondence rows of the patch pairs ``ia`` × ``rows_b`` (query patch, indexed patch)."""
        x = np.empty((len(ia), nf + npd + len(self._strips)))
        x[:, :nf] = fcol[owner]
        x[:, nf:nf + npd] = _columnwise(pd, cues.patches[ia], self._patches[rows_b])
        for m, s in enumerate(self._strips):
            x[:, nf + npd + m] = strip_gap(cues.strips[m][ia], s[rows_b])
        return x

    def uses_ribbon(self, fragment: str, model: MatchModel) -> bool:
        """Whether stage 2½ ranks this fragment's candidates (a boundary profile and a calibrated model)."""
        return model.ribbon is not None and fragment in self.profiles

    def _rank_by_ribbon(self, fragment: str, candidates: list[Candidate], model: MatchModel) -> list[Candidate]:
        """Stage 2½ for one query fragment (which :meth:`uses_ribbon`): colour-ribbon score and
        calibrated probability of each candidate, best first; a candidate without a boundary profile
        keeps its stage-2 probability."""
        n = len(self.profiles)
        if self._population is None or abs(n - self._population_n) > max(2, n // 10):
            self._population, self._population_n = ribbon_population(self.profiles), n
        group = [c for c in candidates if c.other in self.profiles]
        rarity = sample_rarity(self.profiles[fragment], self._population, fragment=fragment)
        s, arc_a, arc_b = ribbon_scores(self.profiles[fragment], [self.profiles[c.other] for c in group], rarity=rarity)
        half = RIBBON_WINDOW_MM / 2
        for c, sc, pr, i, j in zip(group, s, ribbon_probability(s, model.ribbon), arc_a, arc_b):
            if np.isfinite(sc):
                c.ribbon_score, c.probability = float(sc), float(pr)
                # centres of the best run: forwards on the query, backwards on the other
                c.ribbon_arc_mm = (float(i + half), float(j - half))
        return sorted(candidates, key=lambda c: -c.probability)

    def _ribbon_head(self, fragment: str, found: list[Candidate], n: int) -> list[Candidate]:
        """The ``n`` of stage 2's candidates the ribbon ranks: best by the stage-2 logit plus the same-fresco
        ratio (``FRESCO_WEIGHT`` × ratio, as :meth:`_rank_by_fresco` adds it after the ribbon).

        On realistic collections the patch classifier alone is a poor cut: pooled with 384 factory pieces, 31 %
        of RePAIR's true links (20 % of the factory's) were among a fragment's 50 best by stage 2, against 90 %
        (74 %) with the ratio added (docs/matching.md, "What reaches the ribbon"). Only the choice changes:
        the candidates keep their stage-2 probabilities, and a list no longer than ``n`` is kept whole."""
        if len(found) <= n:
            return list(found)
        ratios = self._fresco_ratios(fragment, found)
        if ratios is None:
            return found[:n]
        p = np.clip(np.array([c.probability for c in found], float), 1e-12, 1 - 1e-12)
        key = np.log(p) - np.log1p(-p) + self._ratio_weight() * np.nan_to_num(ratios, nan=0.0)
        key = np.where(np.isfinite(key), key, -np.inf)
        return [found[i] for i in np.argsort(-key, kind="stable")[:n]]

    def _forget_dockings(self, fragment: str) -> None:
        self.dock_hubness.pop(fragment, None)
        self._frames.pop(fragment, None)
        for key in [k for k in self._dockings if fragment in k]:
            del self._dockings[key]
        for key in [k for k in self._paint_pairs if fragment in k]:
            del self._paint_pairs[key]
        for key in [k for k in self._poses if fragment in k]:
            del self._poses[key]
            self._alternatives.pop(key, None)

    def paint_pair(self, fragment: str, other: str) -> float:
        """Paint continuing across the crack between two fragments, mm (cached per pair): the best
        :func:`~common.matching.paint.paint_continuity` over the pair's docking's candidate poses
        (:func:`~common.matching.paint.paint_pair_mm`); NaN when either has no outline or profile."""
        key = _pair(fragment, other)
        if key not in self._paint_pairs:
            if not all(f in self._raw_profiles and f in self.contours for f in key):
                return float("nan")
            if not self._recall(key, paint=True):
                self._dock_pair(key, paint=True)
        return self._paint_pairs[key]

    def docking(self, fragment: str, other: str) -> Docking:
        """``other`` docked against ``fragment`` (pose of ``other`` in ``fragment``'s frame), cached."""
        key = _pair(fragment, other)
        if not self._recall(key, paint=False):
            self._dock_pair(key, paint=self._docks_with_paint(key))
        d = self._dockings[key]
        return d if key[0] == fragment else invert_docking(d)

    def pose(self, fragment: str, other: str) -> Docking:
        """The proposed pose of ``other`` in ``fragment``'s frame: the docking's candidate the learned chooser
        scores best (:func:`~common.matching.pose.learned_pose_scores`: contact, paint continuity and the
        outlines' facing geometry) where the pair was docked with paint, else the best docking."""
        key = _pair(fragment, other)
        d = self._poses.get(key)
        if d is None:
            return self.docking(fragment, other)
        return d if key[0] == fragment else invert_docking(d)

    def docked(self, fragment: str, other: str) -> bool:
        """Whether the pair was docked before: by this index, or by another over the same store (then its
        docking is read into this one's cache)."""
        return self._recall(_pair(fragment, other), paint=False)

    def _docks_with_paint(self, key: tuple[str, str]) -> bool:
        """Whether stage 3 docks this pair with paint (:data:`DOCK_USES_PAINT` and both have a profile)."""
        return DOCK_USES_PAINT and all(f in self._raw_profiles for f in key)

    def _recall(self, key: tuple[str, str], paint: bool) -> bool:
        """Whether the pair's docking is in the cache — with its paint, pose and alternatives if ``paint`` —,
        reading it from :attr:`docking_store` if it is kept there for both fragments' current inputs and
        this docking version (anything else stored is as good as nothing: the pair is docked again)."""
        if key in self._dockings and (not paint or key in self._paint_pairs):
            return True
        inputs = self._inputs.get(key[0]), self._inputs.get(key[1])
        if self.docking_store is None or None in inputs:
            return False
        kept = self.docking_store.docking(*key, *inputs, docking_version())
        if kept is None or (paint and not kept.paint):
            return False
        self._dockings.setdefault(key, Docking(*kept.best))
        if kept.paint:
            self._paint_pairs[key] = kept.paint_mm
            self._poses[key] = Docking(*kept.pose)
            self._alternatives[key] = [Docking(*a) for a in kept.alternatives]
        return True

    def _keep(self, key: tuple[str, str]) -> None:
        """Write the pair's docking (as :meth:`_dock_pair` cached it) to :attr:`docking_store`."""
        inputs = self._inputs.get(key[0]), self._inputs.get(key[1])
        if self.docking_store is None or None in inputs:
            return
        from dataclasses import astuple

        from common.matching.proposals import StoredDocking

        paint = key in self._poses and key in self._paint_pairs
        self.docking_store.put_docking(StoredDocking(
            *key, *inputs, docking_version(), best=astuple(self._dockings[key]), paint=paint,
            paint_mm=self._paint_pairs[key] if paint else float("nan"),
            pose=astuple(self._poses[key]) if paint else None,
            alternatives=[astuple(a) for a in self._alternatives.get(key, [])] if paint else []))

    def _recall_dock_hubness(self, fragments=None) -> None:
        """Read the docking hubness of ``fragments`` (None: every fragment) from :attr:`docking_store`,
        where the last worker to rank each one left it: it replaces this index's value. The first call
        reads every fragment's, so a restarted worker's median (the correction's centre) is the one
        the worker before it had. Values made from other inputs or by another docking version are
        left out."""
        if self.docking_store is None:
            return
        if fragments is None or not self._dock_hubness_recalled:
            fragments, self._dock_hubness_recalled = list(self._order), True
        inputs = {f: self._inputs[f] for f in fragments if self._inputs.get(f) is not None}
        if inputs:
            self.dock_hubness.update(self.docking_store.dock_hubness(inputs, docking_version()))

    def _set_dock_hubness(self, fragment: str, contact_mm, model_version: str | None) -> None:
        """The fragment's docking hubness from the contacts of its docked best (mm): the mean of the best
        :data:`DOCK_HUB_TOP` (unchanged with fewer), written to :attr:`docking_store` where it changed."""
        if len(contact_mm) < DOCK_HUB_TOP:
            return
        value = float(np.sort(np.asarray(contact_mm, float))[-DOCK_HUB_TOP:].mean())
        if self.dock_hubness.get(fragment) == value:
            return
        self.dock_hubness[fragment] = value
        inputs = self._inputs.get(fragment)
        if self.docking_store is not None and inputs is not None:
            self.docking_store.put_dock_hubness(fragment, inputs, docking_version(), value, model_version)

    def alternatives(self, fragment: str, other: str) -> list[Docking]:
        """The pair's other candidate poses, best first (of ``other`` in ``fragment``'s frame; at most
        :data:`~common.matching.pose.ALTERNATIVE_POSES`, none where the pair was not docked with
        paint): what a person steps through when :meth:`pose` is not the join."""
        key = _pair(fragment, other)
        alts = self._alternatives.get(key, [])
        return list(alts) if key[0] == fragment else [invert_docking(d) for d in alts]

    def _frame(self, fragment: str) -> DockingFrame:
        """The fragment's docking frame (kept: its maps and spectra serve all its partners)."""
        frame = self._frames.pop(fragment, None)
        if frame is None:
            frame = DockingFrame(self.contours[fragment])
        self._frames[fragment] = frame   # most recently used last
        return frame

    def _dock_pairs(self, fragment: str, others) -> None:
        """Dock ``fragment`` with each of ``others`` not docked yet, in order of FFT size, so that a turned
        fragment's spectra (:class:`~common.matching.docking.DockingFrame`) are computed once per size."""
        keys = {_pair(fragment, o) for o in others if o in self.contours}
        keys = [k for k in keys if not self._recall(k, paint=self._docks_with_paint(k))]
        for k in sorted(keys, key=lambda k: (self._frame(k[0]).fft_size(self._frame(k[1])), k)):
            if k not in self._dockings:
                self.docking(*k)
            if DOCK_USES_PAINT:
                self.paint_pair(*k)

    def _search(self, key: tuple[str, str], many: bool) -> list[Docking]:
        """The docking search of a pair (the second of ``key`` turned against the first): with ``many``, the
        :data:`DOCK_PAINT_POSES` candidates and :data:`DOCK_MORE_POSES` more that a pair docked with paint
        chooses and offers among, else the single best pose (coarse to fine)."""
        frames = self._frame(key[0]), self._frame(key[1])
        # paint carried across the gap inside the FFT where both have a boundary profile (off by default)
        kw = dict(paint_a=self.paint.get(key[0]), paint_b=self.paint.get(key[1]))
        if many:
            return dock_frames(*frames, n_poses=DOCK_PAINT_POSES, per_angle=DOCK_PAINT_PER_ANGLE,
                               more_poses=DOCK_MORE_POSES, **kw)
        return dock_frames(*frames, n_poses=1, **kw)

    def candidate_poses(self, fragment: str, other: str) -> list[Docking]:
        """Every candidate pose of ``other`` in ``fragment``'s frame that the station's docking of the pair
        chooses and offers among (the search run again; nothing is cached). Whether a right pose is among
        them is the ceiling of any chooser (``pose_reachable`` of :func:`~common.matching.report.evaluate_collection`)."""
        key = _pair(fragment, other)
        docks = self._search(key, many=True)
        return docks if key[0] == fragment else [invert_docking(d) for d in docks]

    def _dock_pair(self, key: tuple[str, str], paint: bool) -> None:
        """Dock a pair once (the second of ``key`` turned against the first) and cache what it gives: the
        pose (the best docking), and with ``paint`` also the paint continuity over the same docking's
        :data:`DOCK_PAINT_POSES` candidate poses — one search for both. Without paint the docking is
        coarse to fine (a single pose)."""
        if paint:
            from common.matching.paint import paint_continuity, paint_field_from_profile
            from common.matching.pose import ALTERNATIVE_POSES, offered_poses, pose_features

            docks = self._search(key, many=True)
            for f in key:
                if f not in self._paint_fields:
                    self._paint_fields[f] = paint_field_from_profile(self.contours[f], self._raw_profiles[f])
            # the paint continuity at every candidate: its best over the first DOCK_PAINT_POSES is the pair's
            # paint evidence (paint.paint_pair_mm), and with the contact and the outlines' facing geometry it
            # chooses the pair's pose among those and orders all the others offered (pose.offered_poses)
            paint_mm = paint_continuity(self._paint_fields[key[0]], self._paint_fields[key[1]],
                                        np.array([(d.angle_deg, d.tx_mm, d.ty_mm) for d in docks], float))
            self._paint_pairs[key] = float(np.max(paint_mm[:DOCK_PAINT_POSES]))
            features = pose_features(docks, paint_mm, self.contours[key[0]], self.contours[key[1]])
            ranked = offered_poses(docks, paint_mm, features, choose_among=DOCK_PAINT_POSES)  # the first is the pose
            self._poses[key] = ranked[0]
            self._alternatives[key] = ranked[1:1 + ALTERNATIVE_POSES]
            self._dockings.setdefault(key, docks[0])
        else:
            self._dockings[key] = self._search(key, many=False)[0]
        self._keep(key)
        # the frames of the least recently docked fragments go first when over budget (never these two)
        budget = DOCK_FRAMES_MB * 2 ** 20
        held = sum(f.nbytes for f in self._frames.values())
        for f in list(self._frames)[:-2]:
            if held <= budget:
                break
            held -= self._frames.pop(f).nbytes

    def uses_docking(self, fragment: str, model: MatchModel) -> bool:
        """Whether stage 3 docks this fragment's candidates (an outline and a calibrated model)."""
        return model.docking is not None and fragment in self.contours

    def _dock_head(self, ranked: list[Candidate], dock_candidates: int) -> list[Candidate]:
        """The candidates stage 3 docks: of the best ``dock_candidates`` after stage 2½, those with an outline."""
        return [c for c in ranked[:dock_candidates] if c.other in self.contours]

    def _rank_by_docking(self, fragment: str, ranked: list[Candidate], model: MatchModel,
                         dock_candidates: int, docked_only: bool = False) -> list[Candidate]:
        """Stage 3 for one query fragment: its best ``dock_candidates`` are docked
        (:func:`~common.matching.docking.dock_outlines`, gap-tolerant), their contact corrected for
        both fragments' docking hubness and calibrated into the join probability (with the earlier
        evidence and the paint, or the model's learned combination); they come first, best first,
        each with its chosen pose (:meth:`pose`) as its alignment. The rest follow, never above them.
        ``docked_only``: of the best ``dock_candidates``, only the pairs docked before (no new docking)."""
        head = self._dock_head(ranked, dock_candidates)
        if docked_only:
            head = [c for c in head if self.docked(fragment, c.other)]
        if not head:
            return ranked
        docked = {id(c) for c in head}
        tail = [c for c in ranked if id(c) not in docked]
        self._dock_pairs(fragment, [c.other for c in head])
        contact = np.array([docking_contact_mm(self.docking(fragment, c.other)) for c in head])
        self._recall_dock_hubness([c.other for c in head])
        self._set_dock_hubness(fragment, contact, model.version)
        centre = float(np.median(list(self.dock_hubness.values()))) if self.dock_hubness else 0.0
        corrected = hub_corrected(contact, self.dock_hubness.get(fragment, centre),
                                  [self.dock_hubness.get(c.other, centre) for c in head], centre)
        paint = np.full(len(head), np.nan)
        if DOCK_USES_PAINT:
            paint = np.array([self.paint_pair(fragment, c.other) for c in head])
        if model.combination is not None:
            # every stage's evidence weighed as learned on synthetic pairs (online.stage_combination)
            prob = model.combined_probability([c.patch_logit for c in head], [c.ribbon_score for c in head],
                                              corrected, paint)
            rescale = float   # a logistic fit already
        else:
            prob = join_probability(_dock_by_rules(head, ribbon_probability(corrected, model.docking), paint, model))
            rescale = join_probability
        for c, k, p, m in zip(head, corrected, prob, paint):
            d = self.docking(fragment, c.other)
            c.docking, c.docking_contact_mm, c.probability, c.paint_mm = d, float(k), float(p), float(m)
            c.alignment = self._docked_alignment(fragment, c.other, float(k))
        head.sort(key=lambda c: -c.probability)
        floor = head[-1].probability
        for c in tail:   # on the head's scale (the same monotone map), never above it
            if np.isfinite(c.probability):
                c.probability = min(float(rescale(c.probability)), floor)
        return head + tail

    def _docked_alignment(self, fragment: str, other: str, score: float) -> Alignment:
        """The proposed pose of a docked pair as a candidate's alignment (:meth:`pose`, chosen by contact and
        paint, with its :meth:`alternatives`); ``score``: the contact corrected for hubness (NaN where the pair
        was docked before but is not among the best this ranking docked)."""
        from common.matching.pose import wrapped_deg   # the docking's angles are in [0, 360): shown in one range

        q = self.pose(fragment, other)
        return Alignment(wrapped_deg(q.angle_deg), q.tx_mm, q.ty_mm, float("nan"), q.contact_mm, q.overlap_mm2, score,
                         tuple((wrapped_deg(a.angle_deg), a.tx_mm, a.ty_mm) for a in self.alternatives(fragment, other)))

    def _fresco_signature(self, fragment: str):
        """The fragment's :class:`~common.matching.fresco.FrescoSignature` (from its boundary profile and
        face colour; cached while its profile is the same object), None without a profile."""
        from common.matching.fresco import profile_signature

        prof = self._raw_profiles.get(fragment)
        cache = self.__dict__.setdefault("_fresco_signatures", {})   # fragment → (profile, signature)
        if prof is None:
            cache.pop(fragment, None)
            return None
        if fragment not in cache or cache[fragment][0] is not prof:
            keys = [d.key for d in _descs()[0]]
            face = self.cues[fragment].values[[keys.index(f"fragment.colour_mean_{c}") for c in "rgb"]]
            cache[fragment] = (prof, profile_signature(prof, face_rgb=face))
        return cache[fragment][1]

    def _rank_by_fresco(self, fragment: str, candidates: list[Candidate]) -> list[Candidate]:
        """Which fresco a piece comes from (:mod:`common.matching.fresco`), after stage 2½: the same-fresco
        log-likelihood ratio of the query and each candidate is added to the candidate's logit
        (``FRESCO_WEIGHT`` × ratio), so it decides with the earlier stages which candidates stage 3 docks
        and stays in their evidence there (``DOCK_KEEPS_EARLIER_EVIDENCE``). Without fitted parameters,
        a weight of 0 or a profile, the order is kept; so it is in a collection of one fresco (:attr:`single_fresco`)."""
        from common.matching import fresco

        if self.single_fresco:
            return candidates
        ratios = self._fresco_ratios(fragment, candidates)
        if ratios is None:
            return candidates
        for c, r in zip(candidates, ratios):
            if np.isfinite(r):
                c.fresco_llr = float(r)
                c.probability = float(fresco.with_fresco(c.probability, c.fresco_llr, self._ratio_weight()))
        return sorted(candidates, key=lambda c: -c.probability if np.isfinite(c.probability) else np.inf)

    def _ratio_signature(self, fragment: str):
        """The fragment's fresco signature where the same-fresco ratio is on (fitted parameters, a weight above 0);
        None when it is off or the fragment has no profile — stages 1, 2½'s cut and the ratio then keep their
        order without it."""
        from common.matching import fresco

        if self._ratio_weight() <= 0 or fresco.FRESCO_LLR is None:
            return None
        return self._fresco_signature(fragment)

    def _ratio_weight(self) -> float:
        """The same-fresco ratio's weight: :attr:`fresco_weight`, else the module's default."""
        from common.matching import fresco

        return fresco.FRESCO_WEIGHT if self.fresco_weight is None else self.fresco_weight

    def _fresco_ratios(self, fragment: str, candidates: list[Candidate]) -> np.ndarray | None:
        """The same-fresco log-likelihood ratio of the query and each candidate (NaN where the candidate has no
        signature or no finite probability); None when the ratio does not apply (:meth:`_ratio_signature`)."""
        from common.matching import fresco

        sig = self._ratio_signature(fragment)
        if sig is None:
            return None
        out = np.full(len(candidates), np.nan)
        for i, c in enumerate(candidates):
            other = self._fresco_signature(c.other)
            if other is not None and np.isfinite(c.probability):
                out[i] = fresco.fresco_llr(sig, other)
        return out

    def rank(self, cues: FragmentCues, others: list[str], model: MatchModel, *,
             ribbon_candidates: int = RIBBON_CANDIDATES, dock_candidates: int = DOCK_CANDIDATES,
             evidence_for: int | None = None, trace: dict | None = None,
             docked_only: bool = False) -> list[Candidate]:
        """Stages 2, 2½ and 3 for one fragment against ``others``, best first.

        Stage 2 orders ``others`` by the patch classifier; where the ribbon applies, its best
        ``ribbon_candidates`` — plus the others stage 2 cannot score because one of the two has no
        valid patch (a small fragment still has a boundary) — are re-ranked by the ribbon and the
        rest dropped, and the same-fresco ratio is added (:meth:`_rank_by_fresco`). Where the model
        has a docking calibration, the best ``dock_candidates`` are then docked and re-ranked
        (:meth:`_rank_by_docking`). ``evidence_for``: attach evidence rows to the best this many of
        stage 2 (None: all). ``trace``: a dict that receives each stage's candidate list as it
        leaves the stage (``"patch"``, ``"ribbon"``, ``"fresco"``, ``"dock"``;
        :func:`common.matching.evaluation.trace_stages`). ``docked_only``: stage 3 uses only the
        pairs among the best ``dock_candidates`` that were docked before (:meth:`rank_again`).
        """
        trace = {} if trace is None else trace
        found = self.score(cues, others, model, evidence_for=evidence_for)
        trace["patch"] = list(found)
        if self.uses_ribbon(cues.fragment, model):
            head = self._ribbon_head(cues.fragment, found, ribbon_candidates)
            scored = {c.other for c in found}
            n_cols = len(model.columns)
            head += [Candidate(cues.fragment, o, float("nan"), -1, -1, np.zeros((0, 2), int), np.zeros((0, n_cols)))
                     for o in others if o != cues.fragment and o not in scored and o in self.profiles]
            found = self._rank_by_ribbon(cues.fragment, head, model)
        trace["ribbon"] = list(found)
        if self.uses_ribbon(cues.fragment, model):   # after stage 2½ only (propose's evidence rows follow it)
            found = self._rank_by_fresco(cues.fragment, found)
        trace["fresco"] = list(found)
        if self.uses_docking(cues.fragment, model) and dock_candidates > 0:
            found = self._rank_by_docking(cues.fragment, found, model, dock_candidates, docked_only)
        trace["dock"] = list(found)
        return found

    def propose(self, cues: FragmentCues, model: MatchModel, *, n_candidates: int = 100, top: int = 10,
                check: int = 3, contour_mm: np.ndarray | None = None,
                ribbon_candidates: int = RIBBON_CANDIDATES, dock: bool = True,
                dock_candidates: int = DOCK_CANDIDATES, also=()) -> list[Candidate]:
        """Stages 1–3 for one fragment: the ``top`` most probable joins, the best ``check`` aligned.

        ``dock=False`` stops after stages 1–2½, neither docking nor aligning (the matcher's first,
        fast answer; it docks next); ``dock_candidates``: how many of the best stage 3 docks (where
        the model has a docking calibration).
        ``also``: fragments to return even when they fall below the ``top`` (a re-ranking updates
        every join it proposed before), after the top ones.
        """
        others = self._candidates_with_hubness(cues, model, n_candidates)
        ribbon = self.uses_ribbon(cues.fragment, model)
        also = set(also)
        ranked = self.rank(cues, others, model, ribbon_candidates=ribbon_candidates,
                           evidence_for=0 if (ribbon or also) else top, dock_candidates=dock_candidates if dock else 0)
        self.rankings[cues.fragment] = [c.other for c in ranked]
        if not dock and self.uses_docking(cues.fragment, model):
            # the first answer of a station that docks next: its probabilities on the share of joins, as the
            # docked answer's will be (the fast stages' over-state, the same-fresco ratio most; monotone)
            for c in ranked:
                if np.isfinite(c.probability):
                    c.probability = float(join_probability(c.probability, FIRST_CALIBRATION))
        ranked = ranked[:top] + [c for c in ranked[top:] if c.other in also]
        for c, m in zip(ranked, self.mutual(cues.fragment, [c.other for c in ranked])):
            c.mutual = m
        if ribbon or also:
            # the evidence rows (what a verdict will teach) of the kept candidates only
            for c in ranked:
                if c.patch_a >= 0 and c.evidence is None:
                    c.evidence = self._evidence(cues, c)
        if dock:
            # a kept join below the docked best whose pair was docked with paint before (from the other side,
            # by an earlier ranking or another worker) still carries that pose: a refit can lift such a join
            # to the top, and its review must show it joined
            for c in ranked:
                if c.alignment is None and self._recall(_pair(cues.fragment, c.other), paint=True):
                    c.alignment = self._docked_alignment(cues.fragment, c.other, float("nan"))
        contour_a = contour_mm if contour_mm is not None else self.contours.get(cues.fragment)
        if contour_a is not None and dock:
            for c in ranked[:check]:
                contour_b = self.contours.get(c.other)
                if contour_b is None or c.alignment is not None:   # docked in stage 3 already
                    continue
                other = self.cues[c.other]
                arcs_a, arcs_b = cues.arc_mm[c.top_pairs[:, 0]], other.arc_mm[c.top_pairs[:, 1]]  # may be empty
                if c.ribbon_arc_mm is not None:
                    arcs_a = np.concatenate([[c.ribbon_arc_mm[0]], arcs_a])
                    arcs_b = np.concatenate([[c.ribbon_arc_mm[1]], arcs_b])   # wrapped by the aligner
                c.alignment = align_fragments(contour_a, contour_b, anchors=(arcs_a, arcs_b) if len(arcs_a) else None)
        return ranked

    def _candidates_with_hubness(self, cues: FragmentCues, model: MatchModel, n_candidates: int) -> list[str]:
        """Stage 1's candidates of a fragment, each with a hubness under ``model``."""
        others = self.candidates(cues, model, n_candidates)
        if self.use_hubness:
            # candidates without a hubness under this model (a restarted worker, a new model) get one
            # first: once per fragment and model, so a stream of new fragments stays O(candidates)
            self.refresh_hubness(others, model, n_candidates=n_candidates)
        return others

    def mutual(self, fragment: str, others) -> list[float]:
        """Mutual proximity of (``fragment``, other) for each of ``others`` from the two fragments' kept
        rankings (:func:`common.matching.mutual.mutual_of`)."""
        from common.matching.mutual import mutual_of

        return mutual_of(self.rankings, fragment, others)

    def rank_again(self, fragments, model: MatchModel, *, knowing: str | None = None,
                   n_candidates: int = 100, dock_candidates: int = DOCK_CANDIDATES,
                   undocked: dict | None = None) -> list[str]:
        """Rank each of ``fragments`` again against its candidates now (stages 1–3, as :meth:`propose`,
        without evidence or alignment) and keep the ranking: what a partner's ranking needs once new
        fragments arrived, for :meth:`mutual`. ``knowing``: only those whose kept ranking lacks this
        fragment (it predates it). Stage 3 uses the dockings made before and docks no new pair (a new
        docking costs ~0.1–0.3 s at real sizes; a fragment proposed on arrival has its best docked
        already, and the new fragment's pair was docked by its own proposal), so a fragment costs
        about a first answer. ``undocked``: a dict that receives, for each ranked fragment whose best
        ``dock_candidates`` hold pairs not docked yet, those others (what :meth:`propose` would dock).
        Stage 3's docking hubness of every fragment ranked is set from its docked best before any of
        them goes through stage 3, so the rankings do not depend on their order.
        Returns the fragments ranked."""
        done = [f for f in fragments if f in self.cues and len(self.cues[f])
                and not (knowing is not None and knowing in self.rankings.get(f, ()))]
        docking = {f: self.uses_docking(f, model) and dock_candidates > 0 for f in done}
        # two passes: stages 1–2½ of all, and each one's docking hubness from its docked best; then
        # stage 3 of each. Every pair is then corrected by both fragments' hubness under this model,
        # whatever order they are ranked in and whatever this worker held before (a restarted worker
        # ranks as the one that stayed)
        before_docking = {}
        for f in done:
            others = self._candidates_with_hubness(self.cues[f], model, n_candidates)
            before_docking[f] = self.rank(self.cues[f], others, model, evidence_for=0, dock_candidates=0)
            if docking[f]:
                head = [c.other for c in self._dock_head(before_docking[f], dock_candidates) if self.docked(f, c.other)]
                self._set_dock_hubness(f, [docking_contact_mm(self.docking(f, o)) for o in head], model.version)
        for f in done:
            ranked = before_docking.pop(f)
            if docking[f]:
                if undocked is not None:
                    new = [c.other for c in self._dock_head(ranked, dock_candidates) if not self.docked(f, c.other)]
                    if new:
                        undocked[f] = new
                ranked = self._rank_by_docking(f, ranked, model, dock_candidates, docked_only=True)
            self.rankings[f] = [c.other for c in ranked]
        return done

    def rank_all(self, model: MatchModel, *, n_candidates: int = 100,
                 dock_candidates: int = DOCK_CANDIDATES) -> dict[str, list[str]]:
        """The full re-rank after a model update: every fragment's hubness under ``model``, then every
        fragment ranked again (:meth:`rank_again`, its ranking kept in :attr:`rankings`) with the
        dockings made before, docking no new pair.

        A pair that enters a fragment's best ``dock_candidates`` under the new model without having
        been docked is left below the docked ones, as :meth:`rank_again` leaves it; docking it costs
        0.3–0.7 s at real sizes, several times the rest of the fragment's re-rank (~0.1 s; docs/matching.md,
        "Scale"), so those dockings do not hold the new rankings: they are returned, to be docked
        afterwards as jobs of their own — :meth:`propose` for each such fragment docks them (the other
        pairs are cached) and gives its ranking as a full proposal would.

        Returns
        -------
        dict fragment → the others in its best ``dock_candidates`` that have no docking yet (only the
        fragments that have such pairs), in the index's order.

        The result depends only on the fragments, the model and the dockings kept: the ribbon's rarity
        reference is made anew of every fragment, and every docking hubness is set under ``model``
        before stage 3 (:meth:`rank_again`), so a worker restarted straight into it ranks as the one
        that stayed.
        """
        self.refresh_hubness(self._order, model, n_candidates=n_candidates)
        self._population = None   # the ribbon's rarity reference made anew of every fragment, as on a restarted worker
        undocked: dict[str, list[str]] = {}
        self.rank_again(list(self._order), model, n_candidates=n_candidates, dock_candidates=dock_candidates,
                        undocked=undocked)
        return undocked


def _pair(a: str, b: str) -> tuple[str, str]:
    """The key of an unordered pair in the index's caches."""
    return (a, b) if a < b else (b, a)


#: Platt scaling of stage 3's fixed combination (:func:`join_probability`): slope and intercept on its logit, fitted
#: on the docked best 12 of every fragment of four factory collections (palettes 10–13, six pompeii walls of 8
#: fragments each, 2,304 candidates, 351 true joins; never RePAIR) by ``tests/bench/bench_join_calibration.py``;
#: refitted in session 25 for the same-fresco ratio's weight 8 (0.2078, -2.3673 at 4)
JOIN_CALIBRATION = {"slope": 0.1794, "intercept": -2.3440}
#: Platt scaling of the matcher's first answer (stages 1–2½ with the same-fresco ratio, before the docking job):
#: fitted on the top 10 of every fragment of the same four factory collections (1,920 candidates, 328 true joins;
#: never RePAIR) by ``tests/bench/bench_join_calibration.py --first`` (session 25)
FIRST_CALIBRATION = {"slope": 0.0951, "intercept": -1.8644}


def join_probability(probability, calibration: dict | None = None) -> np.ndarray:
    """Stage 3's join probability made honest: ``σ(a · logit(p) + b)`` (:data:`JOIN_CALIBRATION`, or
    ``calibration``: :data:`FIRST_CALIBRATION` for the first answer's).

    Stage 3 adds the docking, paint, earlier-stage and same-fresco evidence as independent log odds, so its
    probability saturates (on held-out factory collections, of the candidates at ≥ 0.999 43 % are joins; on
    RePAIR 28 %). Platt's recalibration of that logit (J. Platt, *Probabilistic outputs for support vector
    machines*, 1999) maps it onto the share of true joins among a fragment's docked best; it is monotone, so no
    order changes (docs/matching.md, "The probability over-stated; recalibrated"). The first answer, before the
    docking, over-states alike (mean 0.75 for a share of joins of 0.17 on held-out factory collections).

    >>> round(float(join_probability(0.5)), 3), bool(join_probability(0.999) < 0.999)
    (0.088, True)
    """
    cal = JOIN_CALIBRATION if calibration is None else calibration
    p = np.clip(np.asarray(probability, float), 1e-15, 1 - 1e-15)   # float64 tells nothing closer to 0 or 1 apart
    z = cal["slope"] * (np.log(p) - np.log1p(-p)) + cal["intercept"]
    return 1.0 / (1.0 + np.exp(-z))


def _dock_by_rules(head: list[Candidate], prob: np.ndarray, paint: np.ndarray, model: MatchModel) -> np.ndarray:
    """Stage 3's fixed combination, for models without a learned one: the docking's probability
    ``prob``, plus the earlier stages' logit relative to the docked candidates' mean
    (:data:`DOCK_KEEPS_EARLIER_EVIDENCE`), plus the paint (:func:`~common.matching.paint.with_paint`)."""
    if DOCK_KEEPS_EARLIER_EVIDENCE:
        # the earlier stages' evidence (paint, patches: which fresco a piece comes from) is kept
        # as independent evidence: its logit relative to the docked candidates' mean is added
        # (naive Bayes), so the docking's own calibration sets the level
        before = np.array([c.probability for c in head], float)
        ok = np.isfinite(before)
        if ok.sum() >= 2:
            lb = np.log(np.clip(before, 1e-6, 1 - 1e-6)) - np.log(np.clip(1 - before, 1e-6, 1 - 1e-6))
            shift = np.where(ok, lb - lb[ok].mean(), 0.0)
            lp = np.log(np.clip(prob, 1e-12, 1 - 1e-12)) - np.log(np.clip(1 - prob, 1e-12, 1 - 1e-12))
            prob = 1.0 / (1.0 + np.exp(-(lp + shift)))
    if DOCK_USES_PAINT:
        from common.matching.paint import with_paint

        prob = np.where(np.isfinite(paint), with_paint(prob, np.nan_to_num(paint), model.docking[0]), prob)
    return prob


def _strip_b_rows(strips: np.ndarray) -> np.ndarray:
    """B's side of :func:`_strip_gap_all`, made once per indexed patch, (N, 2W + 1) float32: each
    strip reversed as ``[x…, y…]`` and its squared norm / W last (NaN for a missing strip, whose
    coordinates are zeroed)."""
    n, width = strips.shape[:2]
    miss = np.isnan(strips).any(axis=(1, 2))
    b = np.where(miss[:, None, None], 0.0, strips[:, ::-1, :])
    out = np.empty((n, 2 * width + 1), np.float32)
    out[:, :width], out[:, width:2 * width] = b[:, :, 0], b[:, :, 1]
    out[:, -1] = np.where(miss, np.nan, (b * b).sum(axis=(1, 2)) / width)
    return out


def _strip_gap_all(strips_a: np.ndarray, rows_b: np.ndarray, missing: float = np.nan) -> np.ndarray:
    """:func:`~common.matching.pairs.strip_gap` of every A strip (Na, W, 2) with every B strip
    (as :func:`_strip_b_rows`), (Na, Nb) float32; ``missing`` where either strip is missing.

    The Procrustes sums are matrix products (as in
    :func:`~common.matching.alignment.procrustes_all_pairs`), so no pair is materialised: the
    cosine and sine sums of every pair come from one product ``[[ax, ay], [ay, −ax]] · [bx; by]ᵀ``
    and the rest is done in place. ``2/W`` is folded into A and ``1/W`` into the norms, so the
    residual is ``|a|²/W + |b|²/W − |c + i s|·2/W``. In float32: the strips are centred (norms
    ~100 mm²), so the cancellation costs ~1e-5 mm² against residuals of true pairs ≥ 0.01 mm².
    """
    n_a, width = strips_a.shape[:2]
    miss_a = np.isnan(strips_a).any(axis=(1, 2))
    a = np.where(miss_a[:, None, None], 0.0, strips_a)
    ax, ay = a[:, :, 0] * (2.0 / width), a[:, :, 1] * (2.0 / width)
    cs = np.block([[ax, ay], [ay, -ax]]).astype(np.float32) @ rows_b[:, :-1].T
    cs *= cs
    res = cs[:n_a]
    res += cs[n_a:]
    np.sqrt(res, out=res)          # |c + i s|·2/W: the best rotation's alignment
    np.subtract(((a * a).sum(axis=(1, 2)) / width).astype(np.float32)[:, None], res, out=res)
    norm_b = rows_b[:, -1]
    miss_b = np.isnan(norm_b)
    res += np.where(miss_b, 0.0, norm_b)[None, :]
    np.maximum(res, 0.0, out=res)
    np.sqrt(res, out=res)
    res[miss_a] = missing
    res[:, miss_b] = missing
    return res
