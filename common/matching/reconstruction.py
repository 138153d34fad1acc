"""Confirmed joins assembled into a reconstruction: a pose graph over SE(2) (after thesis §5.8's verdicts).

Every join a conservator confirms keeps the relative pose they saw (:meth:`ProposalStore.record_verdict`):
fragment B's frame in fragment A's, ``p_a = R(angle) @ p_b + t`` (mm, x right, y down; the convention of
:mod:`common.matching.alignment`). The confirmed joins form a graph whose nodes are fragments (their front
face) and whose edges are those measured relative poses. Each connected component is a **cluster**: a part
of the wall put back together.

Solving a cluster (:func:`solve_pose_graph`) finds one pose per fragment, ``X_i = (θ_i, t_i)`` mapping the
fragment's frame into the cluster's frame (``p_cluster = R(θ_i) @ p_i + t_i``), that agrees best with all
its joins. It is the planar pose-graph problem of robot mapping (Lu & Milios 1997; Olson et al. 2006;
Grisetti et al. 2010 "A tutorial on graph-based SLAM"; Kümmerle et al. 2011, g2o):

1. **Initialisation along a spanning tree**: breadth-first from the cluster's root (its smallest
   fragment id, which stays at the identity), composing the joins outward, ``X_b = X_a ∘ Z_ab``;
   the joins the conflicting loops blame (:func:`blame_joins`: fewest joins covering them, the
   latest confirmed first on a tie) are taken only where no other join connects, and start the
   solve with weight 0.
2. **Nonlinear least squares over SE(2)** (``scipy.optimize.least_squares``, trust-region reflective,
   sparse Jacobian): for each join the error of the measured against the predicted relative pose
   (Grisetti et al. 2010, §IV), taken where B's centre ``c`` lands in A's frame,

       e_t = R(θ_a)ᵀ (R(θ_b) c + t_b − t_a) − (R(θ_ab) c + t_ab),    e_θ = wrap(θ_b − θ_a − θ_ab),

   whitened by the join's standard deviations ``sigma_mm`` and ``sigma_deg``, under a robust loss
   (Cauchy by default, scale ``f_scale`` whitened units, on each join's error norm, by iteratively
   reweighted least squares) so one wrong join cannot drag the rest.

Loops are checked on the measurements themselves, before and independently of the solve: every join
closes a loop with the shortest path of other joins between its two fragments. The
loop's composed transform ``Z_01 ∘ Z_12 ∘ … ∘ Z_k0`` is the identity when the joins agree; its
**closure residual** (angle in degrees, translation in mm, in the frame of the loop's first fragment)
is reported for every loop, with its Mahalanobis distance ``χ²`` under the joins' noise model
(covariance propagated to first order through the composition, numerically). A loop whose ``χ²``
exceeds the ``1 − p_value`` quantile of χ²(3) is **conflicting**: at least one of its joins is wrong.
After the robust solve, a join whose whitened residual exceeds the same bound is marked ``suspect``
(the solve gave it up). A wrong join that only links two otherwise separate clusters closes no loop
and cannot be detected from poses alone.

:func:`next_joins` lists a cluster's open edges: pending proposals between a member and a fragment
outside it, most probable first, with the pose the newcomer would take in the cluster's frame.
:func:`compose_cluster` warps each fragment's albedo into the cluster frame at its solved pose, and
:func:`reconstruction_document` is the JSON of poses (``docs/storage.md``, "Reconstruction JSON").
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping, MutableMapping

import cv2
import numpy as np
from scipy import sparse
from scipy.optimize import least_squares
from scipy.stats import chi2 as _chi2

from common.matching.proposals import order_key
from common.web.compose import relative_pose  # B in A from both poses (its users take it from here too)

#: JSON schema name and version of :func:`reconstruction_document`
SCHEMA = "tessera.reconstruction"
SCHEMA_VERSION = 1
#: default noise model of a confirmed join's pose (standard deviations)
SIGMA_MM = 1.0
SIGMA_DEG = 1.0
#: a loop (or a join after the solve) beyond this tail probability of χ²(3) is flagged
P_VALUE = 1e-4
#: at most this many reweighting rounds of the robust solve
IRLS_ROUNDS = 25
#: a newcomer docked against its whole cluster fits a corner where it faces at least two members there, each
#: along this much outline (mm): that pose is then offered beside the pair's own (:func:`dock_next_joins`)
CLUSTER_FACING_MM = 10.0
FRAME = ("p_cluster = R(angle_deg) @ p_fragment + (tx_mm, ty_mm); mm, x right, y down; a fragment's frame has "
         "x = column * pixel_mm, y = row * pixel_mm of its front RGBN image")


# -- data --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Join:
    """A confirmed join: fragment B's frame in fragment A's, ``p_a = R(angle_deg) @ p_b + (tx_mm, ty_mm)``."""

    fragment_a: str
    fragment_b: str
    angle_deg: float
    tx_mm: float
    ty_mm: float
    time: float | None = None
    by: str | None = None
    proposal_id: int | None = None

    @property
    def pair(self) -> tuple[str, str]:
        return (self.fragment_a, self.fragment_b)


@dataclass
class Loop:
    """A loop of joins and how far its composed transform is from the identity.

    ``fragments`` in loop order (the last joins back to the first); ``joins`` the stored pairs
    ``(a, b)`` along it; ``residual_deg`` and ``residual_mm`` the closure error (translation in the
    first fragment's frame); ``chi2`` its Mahalanobis distance under the noise model; ``conflicting``
    when ``chi2`` exceeds the bound.
    """

    fragments: list[str]
    joins: list[tuple[str, str]]
    residual_deg: float
    residual_mm: float
    chi2: float
    conflicting: bool


@dataclass
class Cluster:
    """A connected component of confirmed joins, solved.

    Attributes
    ----------
    id : str
        ``"C:" + root`` (the root is the smallest fragment id: the cluster's frame is its frame).
    root : str
    fragments : list of str
        Sorted fragment ids.
    poses : dict fragment -> (angle_deg, tx_mm, ty_mm)
        Each fragment's frame in the cluster frame (``p_cluster = R(angle) p + t``).
    joins : list of Join
    loops : list of Loop
    residuals : dict (a, b) -> {"mm", "deg", "whitened", "suspect"}
        Each join's error at the solved poses.
    blamed : list of (a, b)
        Joins the conflicting loops point at (:func:`blame_joins`).
    cost, iterations, solve_s : float, int, float
        Final robust cost ``½ Σ ρ(|e|²)``, function evaluations, CPU seconds of the solve.
    """

    id: str
    root: str
    fragments: list[str]
    poses: dict[str, tuple[float, float, float]]
    joins: list[Join]
    loops: list[Loop] = field(default_factory=list)
    residuals: dict = field(default_factory=dict)
    blamed: list = field(default_factory=list)
    cost: float = 0.0
    iterations: int = 0
    solve_s: float = 0.0

    @property
    def conflicting_loops(self) -> list[Loop]:
        return [lp for lp in self.loops if lp.conflicting]


# -- SE(2) -------------------------------------------------------------------------------------
def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _compose(p, q):
    """(θ, x, y) ∘ (θ, x, y): ``p`` applied after ``q``'s frame change, i.e. ``X_p X_q``."""
    c, s = math.cos(p[0]), math.sin(p[0])
    return (p[0] + q[0], p[1] + c * q[1] - s * q[2], p[2] + s * q[1] + c * q[2])


def _inverse(p):
    c, s = math.cos(p[0]), math.sin(p[0])
    return (-p[0], -(c * p[1] + s * p[2]), -(-s * p[1] + c * p[2]))


def _rad(join: Join):
    return (math.radians(join.angle_deg), float(join.tx_mm), float(join.ty_mm))


# -- reading the verdicts ----------------------------------------------------------------------
def confirmed_joins(store) -> tuple[list[Join], list[tuple[str, str]]]:
    """Confirmed joins of a :class:`~common.matching.proposals.ProposalStore`, with the pose seen.

    A pair counts when its latest verdict is ``confirmed``; its pose is the one kept with that
    verdict (the pose the person saw), else the proposal's current pose.

    Returns
    -------
    joins : list of Join
    unposed : list of (a, b)
        Confirmed pairs without any pose (verdicts recorded before poses were kept): they cannot be
        placed and are listed, not dropped silently.
    """
    latest = {}
    for v in store.verdicts():
        latest[(v.fragment_a, v.fragment_b)] = v
    joins, unposed = [], []
    for (a, b), v in sorted(latest.items()):
        if v.verdict != "confirmed":
            continue
        pose = v.pose
        if not pose or pose.get("angle_deg") is None:
            prop = store.get(a, b)
            pose = ({"angle_deg": prop.angle_deg, "tx_mm": prop.tx_mm, "ty_mm": prop.ty_mm}
                    if prop is not None and prop.angle_deg is not None else None)
        if pose is None:
            unposed.append((a, b))
            continue
        joins.append(Join(a, b, float(pose["angle_deg"]), float(pose["tx_mm"]), float(pose["ty_mm"]),
                          time=v.time, by=v.by, proposal_id=v.proposal_id))
    return joins, unposed


# -- graph -------------------------------------------------------------------------------------
def _check_joins(joins: Iterable[Join]) -> list[Join]:
    out, seen = [], set()
    for j in joins:
        if not isinstance(j, Join):
            raise ValueError(f"joins must be Join records, got {type(j).__name__}")
        if j.fragment_a == j.fragment_b:
            raise ValueError(f"join of fragment {j.fragment_a!r} with itself")
        key = tuple(sorted(j.pair))
        if key in seen:
            raise ValueError(f"two joins for the pair {key}: give one pose per pair")
        seen.add(key)
        if not all(np.isfinite([j.angle_deg, j.tx_mm, j.ty_mm])):
            raise ValueError(f"join {j.pair} has a non-finite pose ({j.angle_deg}, {j.tx_mm}, {j.ty_mm})")
        out.append(j)
    return out


def _adjacency(joins: list[Join]) -> dict[str, list[tuple[str, int]]]:
    adj: dict[str, list[tuple[str, int]]] = {}
    for k, j in enumerate(joins):
        adj.setdefault(j.fragment_a, []).append((j.fragment_b, k))
        adj.setdefault(j.fragment_b, []).append((j.fragment_a, k))
    for v in adj.values():
        v.sort()
    return adj


def find_clusters(joins: Iterable[Join]) -> list[list[str]]:
    """Connected components of the join graph: sorted fragment ids, largest cluster first.

    Examples
    --------
    >>> find_clusters([Join("a", "b", 0, 1, 0), Join("c", "d", 0, 1, 0), Join("b", "e", 0, 1, 0)])
    [['a', 'b', 'e'], ['c', 'd']]
    """
    adj = _adjacency(_check_joins(joins))
    seen, out = set(), []
    for start in sorted(adj):
        if start in seen:
            continue
        comp, queue = [], deque([start])
        seen.add(start)
        while queue:
            n = queue.popleft()
            comp.append(n)
            for m, _ in adj[n]:
                if m not in seen:
                    seen.add(m)
                    queue.append(m)
        out.append(sorted(comp))
    return sorted(out, key=lambda c: (-len(c), c[0]))


def _step(join: Join, frm: str):
    """The transform taking the next fragment's frame into ``frm``'s along ``join``."""
    z = _rad(join)
    return z if frm == join.fragment_a else _inverse(z)


def _spanning_tree(root: str, adj, joins, avoid: set[int] = frozenset()) -> tuple[dict, set[int]]:
    """Breadth-first poses from ``root``; joins in ``avoid`` are used only where nothing else connects."""
    poses, tree = {root: (0.0, 0.0, 0.0)}, set()
    for allowed in (lambda k: k not in avoid, lambda k: True):
        queue = deque(poses)
        while queue:
            n = queue.popleft()
            for m, k in adj[n]:
                if m not in poses and allowed(k):
                    poses[m] = _compose(poses[n], _step(joins[k], n))
                    tree.add(k)
                    queue.append(m)
    return poses, tree


def _shortest_path(adj, start: str, goal: str, skip: int) -> list[tuple[str, int]] | None:
    """Fewest joins from start to goal without join ``skip``: [(fragment, join index taken to it)]."""
    prev = {start: None}
    queue = deque([start])
    while queue:
        n = queue.popleft()
        if n == goal:
            break
        for m, k in adj[n]:
            if k != skip and m not in prev:
                prev[m] = (n, k)
                queue.append(m)
    if goal not in prev:
        return None
    path, n = [], goal
    while prev[n] is not None:
        p, k = prev[n]
        path.append((n, k))
        n = p
    return path[::-1]


def _loop_transform(steps, joins, perturb=None):
    """Compose a loop's joins; ``steps`` = [(from fragment, join index)]; ``perturb`` = (i, dim, h)."""
    t = (0.0, 0.0, 0.0)
    for i, (frm, k) in enumerate(steps):
        z = list(_rad(joins[k]))
        if perturb is not None and perturb[0] == i:
            z[perturb[1]] += perturb[2]
        j = joins[k]
        t = _compose(t, tuple(z) if frm == j.fragment_a else _inverse(tuple(z)))
    return np.array([_wrap(t[0]), t[1], t[2]])


def closure_loops(joins: Iterable[Join], *, sigma_mm: float = SIGMA_MM, sigma_deg: float = SIGMA_DEG,
                  p_value: float = P_VALUE, centres_mm: Mapping | None = None) -> list[Loop]:
    """The shortest loop through every join of the graph, and its closure.

    Each join ``(a, b)`` closes a loop with the shortest chain of other joins from ``b`` back to ``a``
    (fewest joins, breadth-first); loops found twice are kept once. Every join that lies on any
    cycle is thus checked in its tightest loop, and the loops span the graph's cycle space. A
    join on no cycle (a bridge) is checked by none. A consistent set of joins composes to the
    identity around every loop.

    Parameters
    ----------
    joins : iterable of Join
    sigma_mm, sigma_deg : float
        Standard deviation of each join's translation (per axis, mm) and angle (degrees).
    p_value : float
        A loop is conflicting when its χ² exceeds the ``1 - p_value`` quantile of χ²(3).
    centres_mm : mapping fragment -> (x, y), optional
        A point of each fragment's frame (its centre, mm) about which a join's angle error turns
        B (see :func:`solve_pose_graph`); default the frame origin.

    Returns
    -------
    list of Loop, worst (largest χ²) first.

    References
    ----------
    Olson, Leonard & Teller 2006, "Fast iterative alignment of pose graphs with poor initial
    estimates" (loops of relative-pose constraints); Grisetti et al. 2010, "A tutorial on
    graph-based SLAM", §IV (the SE(2) error and its information matrix).

    Examples
    --------
    >>> js = [Join("a", "b", 90, 10, 0), Join("b", "c", 45, 10, 0), Join("a", "c", 135, 10, 10)]
    >>> [round(lp.residual_mm, 6) for lp in closure_loops(js)]
    [0.0]
    """
    joins = _check_joins(joins)
    _check_noise(sigma_mm, sigma_deg, p_value)
    adj = _adjacency(joins)
    bound = float(_chi2.ppf(1.0 - p_value, 3))
    q = _anchors(joins, centres_mm)
    loops, seen = [], set()
    for k, j in enumerate(joins):
        path = _shortest_path(adj, j.fragment_b, j.fragment_a, skip=k)
        if path is None:
            continue        # a bridge: no loop checks this join
        key = frozenset([k] + [kk for _, kk in path])
        if key in seen:
            continue
        seen.add(key)
        # loop a -> b (this join) then back along the path to a
        steps, frm = [(j.fragment_a, k)], j.fragment_b
        fragments = [j.fragment_a]
        for node, kk in path:
            steps.append((frm, kk))
            fragments.append(frm)
            frm = node
        r = _loop_transform(steps, joins)
        # first-order covariance of the composed transform, by central differences per join parameter
        J = np.zeros((3, 3 * len(steps)))
        for i in range(len(steps)):
            for d in range(3):
                h = 1e-6 if d == 0 else 1e-4
                J[:, 3 * i + d] = (_loop_transform(steps, joins, (i, d, h)) -
                                   _loop_transform(steps, joins, (i, d, -h))) / (2 * h)
        cov_edges = np.zeros((3 * len(steps), 3 * len(steps)))
        for i, (_, kk) in enumerate(steps):
            cov_edges[3 * i:3 * i + 3, 3 * i:3 * i + 3] = _join_covariance(joins[kk], q[kk], sigma_mm, sigma_deg)
        cov = J @ cov_edges @ J.T
        x2 = float(r @ np.linalg.solve(cov, r))
        loops.append(Loop(fragments=fragments, joins=[joins[kk].pair for _, kk in steps],
                          residual_deg=abs(math.degrees(float(r[0]))), residual_mm=float(math.hypot(r[1], r[2])),
                          chi2=x2, conflicting=x2 > bound))
    return sorted(loops, key=lambda lp: -lp.chi2)


def _anchors(joins: list[Join], centres_mm: Mapping | None) -> np.ndarray:
    """(K, 2): each join's anchor, fragment B's centre in B's frame (mm), or the origin."""
    centres_mm = centres_mm or {}
    q = np.zeros((len(joins), 2))
    for k, j in enumerate(joins):
        if j.fragment_b in centres_mm:
            c = np.asarray(centres_mm[j.fragment_b], float)
            if c.shape != (2,) or not np.all(np.isfinite(c)):
                raise ValueError(f"centres_mm[{j.fragment_b!r}] must be a finite (x, y), got {centres_mm[j.fragment_b]!r}")
            q[k] = c
    return q


def _join_covariance(join: Join, anchor, sigma_mm: float, sigma_deg: float) -> np.ndarray:
    """Covariance of a join's (θ rad, tx, ty) when B turns by N(0, σ_θ) about its anchor and shifts by N(0, σ_mm)."""
    a = math.radians(join.angle_deg)
    c, s = math.cos(a), math.sin(a)
    p = np.array([c * anchor[0] - s * anchor[1] + join.tx_mm, s * anchor[0] + c * anchor[1] + join.ty_mm])
    d = np.array([join.tx_mm, join.ty_mm]) - p          # origin of B relative to its anchor, in A's frame
    J = np.array([[1.0, 0.0, 0.0], [-d[1], 1.0, 0.0], [d[0], 0.0, 1.0]])
    return J @ np.diag([math.radians(sigma_deg) ** 2, sigma_mm ** 2, sigma_mm ** 2]) @ J.T


def _check_noise(sigma_mm, sigma_deg, p_value):
    if not (np.isfinite(sigma_mm) and sigma_mm > 0):
        raise ValueError(f"sigma_mm must be a positive number, got {sigma_mm}")
    if not (np.isfinite(sigma_deg) and sigma_deg > 0):
        raise ValueError(f"sigma_deg must be a positive number, got {sigma_deg}")
    if not (0.0 < p_value < 1.0):
        raise ValueError(f"p_value must be in (0, 1), got {p_value}")


# -- the solve ---------------------------------------------------------------------------------
def _residuals(x, fixed, index, ia, ib, z, w, q):
    """Whitened SE(2) errors of every join (3 per join) for the free poses ``x``.

    ``q`` (K, 2): each join's anchor in B's frame; the translation error is where the anchor lands
    in A's frame (from the poses) minus where the join puts it.
    """
    P = np.vstack([fixed, x.reshape(-1, 3)])   # row 0 = root
    pa, pb = P[index[ia]], P[index[ib]]
    cb, sb = np.cos(pb[:, 0]), np.sin(pb[:, 0])
    # the anchor in the cluster frame, then in A's frame
    gx = cb * q[:, 0] - sb * q[:, 1] + pb[:, 1] - pa[:, 1]
    gy = sb * q[:, 0] + cb * q[:, 1] + pb[:, 2] - pa[:, 2]
    ca, sa = np.cos(pa[:, 0]), np.sin(pa[:, 0])
    cz, sz = np.cos(z[:, 0]), np.sin(z[:, 0])
    ex = ca * gx + sa * gy - (cz * q[:, 0] - sz * q[:, 1] + z[:, 1])
    ey = -sa * gx + ca * gy - (sz * q[:, 0] + cz * q[:, 1] + z[:, 2])
    et = _wrap(pb[:, 0] - pa[:, 0] - z[:, 0])
    return np.column_stack([et * w[0], ex * w[1], ey * w[1]]).ravel()


def blame_joins(joins: Iterable[Join], loops: Iterable[Loop]) -> list[tuple[str, str]]:
    """The fewest joins that explain every conflicting loop, picked greedily.

    Repeatedly blames the join that lies on the most conflicting loops not yet explained; a tie goes
    to the join confirmed last (``time``; then the later in ``joins``) — the loop closed before it
    came. A join on a conflicting loop is not necessarily wrong: when two joins are equally
    supported, poses alone cannot tell which one is, and this only says which one to set aside first.

    Returns
    -------
    list of (a, b), in the order blamed.
    """
    joins = list(joins)
    rank = {j.pair: (j.time if j.time is not None else -math.inf, k) for k, j in enumerate(joins)}
    open_loops = [set(lp.joins) for lp in loops if lp.conflicting]
    blamed = []
    while open_loops:
        count: dict = {}
        for lp in open_loops:
            for p in lp:
                count[p] = count.get(p, 0) + 1
        worst = max(count, key=lambda p: (count[p], rank.get(p, (-math.inf, -1))))
        blamed.append(worst)
        open_loops = [lp for lp in open_loops if worst not in lp]
    return blamed


def _rho(s2, loss, f):
    """Robust cost of squared whitened errors ``s2`` (Triggs et al. 2000; scipy's definitions)."""
    if loss == "huber":
        return np.where(s2 <= f * f, s2, 2 * f * np.sqrt(s2) - f * f)
    if loss == "cauchy":
        return f * f * np.log1p(s2 / (f * f))
    return s2


def _robust_weight(s2, loss, f):
    """IRLS weight ``ρ'(s²)`` of each join (1 for plain least squares)."""
    if loss == "huber":
        return np.where(s2 <= f * f, 1.0, f / np.sqrt(np.maximum(s2, 1e-300)))
    if loss == "cauchy":
        return 1.0 / (1.0 + s2 / (f * f))
    return np.ones_like(s2)


def solve_pose_graph(joins: Iterable[Join], *, sigma_mm: float = SIGMA_MM, sigma_deg: float = SIGMA_DEG,
                     loss: str = "cauchy", f_scale: float = 3.0, p_value: float = P_VALUE,
                     centres_mm: Mapping | None = None, max_nfev: int = 50, refine: bool = True,
                     alternatives: int = 40) -> list[Cluster]:
    """Solve every cluster of confirmed joins: one pose per fragment in its cluster's frame.

    Parameters
    ----------
    joins : iterable of Join
        At most one per fragment pair (``p_a = R(angle) p_b + t``, mm).
    sigma_mm, sigma_deg : float
        Standard deviations of a join's translation (per axis, at fragment B's centre) and angle:
        the residuals are divided by them.
    loss : {"cauchy", "huber", "linear"}
        Robust loss ρ of each join's whitened error norm (``"linear"``: plain least squares),
        minimised by iteratively reweighted least squares: each round solves the weighted problem
        with ``least_squares``, then re-weights every join by ``ρ'(|e|²)``.
    f_scale : float
        Where the loss turns robust, in whitened units (3 = three standard deviations).
    p_value : float
        Loops and joins beyond the ``1 - p_value`` quantile of χ²(3) are flagged.
    centres_mm : mapping fragment -> (x, y), optional
        Each fragment's centre in its own frame (mm), e.g. its mask's centroid. A join's
        translation error is measured where B's centre lands rather than at B's frame origin (an
        image corner, up to a fragment's diagonal away), so a small turn of a large piece is not
        mistaken for a large shift. Default: the frame origins.
    max_nfev : int
        Cap on function evaluations of each reweighting round.
    refine : bool
        False: return the spanning-tree initialisation unsolved (to see what the solve adds).
    alternatives : int
        When a cluster has conflicting loops on at most this many joins, each of those joins is
        tried as the one set aside first (with :func:`blame_joins` for the loops it does not
        explain): the spanning-tree start of least robust cost is solved too, and preferred to the
        greedy blame's solution only if it lowers the robust cost by more than ``f_scale² / 2`` (one
        join at the loss's scale); its set-aside joins become the cluster's ``blamed``. Two joins
        equally supported give costs equal up to noise: the greedy blame (on most loops, then
        confirmed last) is kept.

    Returns
    -------
    list of Cluster, largest first. A cluster's root (smallest id) sits at the identity.

    Notes
    -----
    Variables are ``(θ, x, y)`` per fragment except the root (the gauge). The robust loss is applied
    per join (to the norm of its 3 whitened errors) by reweighting rather than through
    ``least_squares``' own ``loss``, which treats each error component apart and, with one grossly
    wrong join, took thousands of evaluations (6,822, 23 s CPU) on the 150-fragment wall. Measuring the
    translation at B's centre ``c``, ``e_t = R_aᵀ(R_b c + t_b − t_a) − (R_ab c + t_ab)``, is the
    g2o error with a full (non-diagonal) information matrix for a pose whose uncertainty is a turn
    about B's centre and a shift. The Jacobian's sparsity
    (each join touches its two fragments) is given to the trust-region solver, which then
    estimates it with a few grouped finite differences. Grisetti et al.'s ``X_i`` is ``poses[i]``,
    their ``z_ij`` a join's pose.

    References
    ----------
    Lu & Milios 1997; Olson et al. 2006 (ICRA); Grisetti, Kümmerle, Stachniss & Burgard 2010,
    "A tutorial on graph-based SLAM", IEEE Intelligent Transportation Systems Magazine 2(4); Kümmerle
    et al. 2011, "g2o: a general framework for graph optimization", ICRA.

    Examples
    --------
    >>> js = [Join("a", "b", 90, 10, 0), Join("b", "c", 45, 10, 0), Join("a", "c", 135, 10, 10)]
    >>> [round(v, 6) + 0.0 for v in solve_pose_graph(js)[0].poses["c"]]
    [135.0, 10.0, 10.0]
    """
    joins = _check_joins(joins)
    _check_noise(sigma_mm, sigma_deg, p_value)
    if not (np.isfinite(f_scale) and f_scale > 0):
        raise ValueError(f"f_scale must be a positive number, got {f_scale}")
    if loss not in ("linear", "huber", "cauchy"):
        raise ValueError(f"loss must be one of linear, huber, cauchy; got {loss!r}")
    adj = _adjacency(joins)
    loops = closure_loops(joins, sigma_mm=sigma_mm, sigma_deg=sigma_deg, p_value=p_value, centres_mm=centres_mm)
    q_all = _anchors(joins, centres_mm)
    row_of = {j.pair: k for k, j in enumerate(joins)}
    # the initialisation avoids joins of conflicting loops where the tree can go round them
    blamed = blame_joins(joins, loops)
    avoid = {row_of[p] for p in blamed}
    bound = math.sqrt(float(_chi2.ppf(1.0 - p_value, 3)))
    w = (1.0 / math.radians(sigma_deg), 1.0 / sigma_mm)
    clusters = []
    for comp in find_clusters(joins):
        t0 = time.process_time()
        root = comp[0]
        members = set(comp)
        mine = [j for j in joins if j.fragment_a in members]
        order = [root] + [f for f in comp if f != root]
        index = {f: i for i, f in enumerate(order)}
        ia = np.array([j.fragment_a for j in mine])
        ib = np.array([j.fragment_b for j in mine])
        lookup = np.vectorize(index.__getitem__, otypes=[int])
        ia_i, ib_i = lookup(ia), lookup(ib)
        z = np.array([_rad(j) for j in mine])
        q = q_all[[row_of[j.pair] for j in mine]]
        fixed = np.zeros((1, 3))
        ident = np.arange(len(order))
        args = (fixed, ident, ia_i, ib_i, z, w, q)
        # Jacobian sparsity: rows of join k depend on the free variables of its two fragments
        rows, cols = [], []
        for k in range(len(mine)):
            for f in (ia_i[k], ib_i[k]):
                if f == 0:
                    continue
                for r in range(3):
                    rows += [3 * k + r] * 3
                    cols += [3 * (f - 1), 3 * (f - 1) + 1, 3 * (f - 1) + 2]
        pattern = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)),
                                    shape=(3 * len(mine), 3 * (len(order) - 1))).tocsr()
        pattern.data[:] = 1

        def start(blame: list) -> np.ndarray:
            init, _ = _spanning_tree(root, adj, joins, {row_of[p] for p in blame})
            return np.array([init[f] for f in order[1:]], float).ravel()

        def run(blame: list) -> tuple[np.ndarray, float, int]:
            """Start along a tree avoiding the blamed joins, with them switched off; reweight to convergence."""
            x = start(blame)
            if not (len(x) and refine):
                return x, 0.0, 0
            weights, nfev = np.array([1e-6 if j.pair in blame else 1.0 for j in mine]), 0
            for _ in range(IRLS_ROUNDS if loss != "linear" else 1):
                sw = np.repeat(np.sqrt(weights), 3)
                sol = least_squares(lambda v: _residuals(v, *args) * sw, x, jac_sparsity=pattern, method="trf",
                                    x_scale="jac", max_nfev=max_nfev)
                x, nfev = sol.x, nfev + int(sol.nfev)
                s2 = np.sum(_residuals(x, *args).reshape(-1, 3) ** 2, axis=1)
                new = _robust_weight(s2, loss, f_scale)
                done = np.max(np.abs(new - weights)) < 1e-3
                weights = new
                if done:
                    break
            return x, 0.5 * float(np.sum(_rho(s2, loss, f_scale))), nfev

        mine_loops = [lp for lp in loops if lp.fragments[0] in members]
        chosen = [p for p in blamed if p[0] in members]
        x, cost, nfev = run(chosen)
        conflicting = [lp for lp in mine_loops if lp.conflicting]
        candidates = sorted({p for lp in conflicting for p in lp.joins})
        if conflicting and refine and loss != "linear" and len(candidates) <= alternatives:
            # each join of the conflicting loops set aside first in turn: the start of least robust
            # cost is solved, and kept if it beats the greedy blame by more than one join's worth
            best, best_cost = None, math.inf
            for cand in candidates:
                blame = [cand] + blame_joins(mine, [lp for lp in conflicting if cand not in lp.joins])
                if blame == chosen:
                    continue
                s2 = np.sum(_residuals(start(blame), *args).reshape(-1, 3) ** 2, axis=1)
                c0 = float(np.sum(_rho(s2, loss, f_scale)))
                if c0 < best_cost:
                    best, best_cost = blame, c0
            if best is not None:
                x2, cost2, nfev2 = run(best)
                nfev += nfev2
                if cost2 < cost - 0.5 * f_scale ** 2:
                    x, cost, chosen = x2, cost2, best
        P = np.vstack([fixed, x.reshape(-1, 3)])
        poses = {f: (math.degrees(float(_wrap(P[i, 0]))), float(P[i, 1]), float(P[i, 2])) for f, i in index.items()}
        r = _residuals(x, fixed, ident, ia_i, ib_i, z, w, q).reshape(-1, 3)
        residuals = {}
        for k, j in enumerate(mine):
            white = float(np.linalg.norm(r[k]))
            residuals[j.pair] = {"mm": float(np.hypot(r[k, 1], r[k, 2]) / w[1]),
                                 "deg": float(abs(math.degrees(r[k, 0] / w[0]))),
                                 "whitened": white, "suspect": white > bound}
        clusters.append(Cluster(id=f"C:{root}", root=root, fragments=comp, poses=poses, joins=mine,
                                loops=mine_loops, residuals=residuals, blamed=chosen,
                                cost=cost, iterations=nfev, solve_s=time.process_time() - t0))
    return clusters


# -- open edges --------------------------------------------------------------------------------
def dock_newcomer(cluster: Cluster, member: str, newcomer: str, pieces: Mapping, *,
                  outline: np.ndarray | None = None) -> tuple[tuple, list[str]]:
    """A newcomer's pose in the cluster frame, docked against the whole cluster instead of one member.

    Where a newcomer fits into a corner of a cluster, two members' outlines hold it at once and pin
    where it sits along either crack, which one member alone leaves open (docs/matching.md, "Docking
    against a confirmed cluster": with :func:`next_joins`' rule, right within 5° and 5 mm for 0.45 of the
    newcomers in a corner of three test walls' clusters against 0.23 at their proposals' poses). The
    members are placed at their solved poses and merged, their
    lost material closed (:func:`common.matching.docking.cluster_outline`); the newcomer is docked against
    that outline as stage 3 docks a pair (its 30 candidates, :func:`~common.matching.docking.dock_outlines`)
    and the learned chooser picks among them (:func:`~common.matching.pose.learned_pose_scores`: contact,
    the paint continuing from ``member``, the facing geometry against the cluster).
    :func:`dock_newcomer_members` does it for several members at once, docking once.

    Parameters
    ----------
    cluster : Cluster
    member : str
        The member the proposal joins the newcomer to (the paint is scored across its crack).
    newcomer : str
    pieces : mapping fragment -> (contour_mm, paint field or None)
        Outlines (each in its fragment's frame, mm) of every member and the newcomer, and their paint
        fields (:func:`~common.matching.paint.paint_field_from_profile`).
    outline : (K, 2) array, optional
        The cluster's merged outline in its frame, when the caller docks several newcomers against it
        (default: made here, :func:`~common.matching.docking.cluster_outline`).

    Returns
    -------
    pose : (angle_deg, tx_mm, ty_mm)
        The newcomer's frame in the cluster frame.
    faced : list of str
        The members it faces along at least :data:`CLUSTER_FACING_MM` of outline at that pose.
    """
    return dock_newcomer_members(cluster, [member], newcomer, pieces, outline=outline)[member]


def dock_newcomer_members(cluster: Cluster, members: Iterable[str], newcomer: str, pieces: Mapping, *,
                          outline: np.ndarray | None = None) -> dict[str, tuple[tuple, list[str]]]:
    """:func:`dock_newcomer` for a newcomer proposed to several members of one cluster, docked once.

    The docking against the cluster's outline (its candidates and their contact and facing geometry) is
    the same whichever member a proposal names; the choice among the candidates is not, since the paint
    scored is the paint continuing from that member across its crack. So the newcomer is docked once and
    the chooser picks for each member: each answer is :func:`dock_newcomer`'s for that member (the same
    pose for all where no paint is scored, as without paint fields).

    Parameters
    ----------
    cluster, newcomer, pieces, outline
        As for :func:`dock_newcomer`.
    members : iterable of str
        Members the newcomer is proposed to.

    Returns
    -------
    dict member -> (pose, faced)
        :func:`dock_newcomer`'s answer for each member.
    """
    from common.matching.docking import dock_outlines
    from common.matching.facing import facing_geometry
    from common.matching.index import DOCK_PAINT_PER_ANGLE, DOCK_PAINT_POSES
    from common.matching.paint import paint_continuity
    from common.matching.pose import learned_pose_scores, pose_features

    members = list(dict.fromkeys(members))
    missing = [f for f in [*cluster.fragments, newcomer] if f not in pieces]
    outside = [m for m in members if m not in cluster.poses]
    if missing or not members or outside or newcomer in cluster.poses:
        raise ValueError(f"dock_newcomer needs the outline of every member and of a newcomer outside the cluster; "
                         f"missing {missing[:5]}, member {(outside or members or [None])[0]!r} in cluster: "
                         f"{bool(members) and not outside}, newcomer {newcomer!r} in cluster: {newcomer in cluster.poses}")
    if outline is None:
        outline = _cluster_outline(cluster, pieces)
    contour_n, paint_n = pieces[newcomer]
    docks = dock_outlines(outline, contour_n, n_poses=DOCK_PAINT_POSES, per_angle=DOCK_PAINT_PER_ANGLE)
    in_cluster = [(math.radians(d.angle_deg), d.tx_mm, d.ty_mm) for d in docks]
    faced_at: dict[int, list[str]] = {}
    out = {}
    for member in members:
        paint = np.zeros(len(docks))
        to_member = _inverse(_deg_to_rad(cluster.poses[member]))
        if pieces[member][1] is not None and paint_n is not None:
            paint = paint_continuity(pieces[member][1], paint_n,
                                     _degrees([_compose(to_member, x) for x in in_cluster]))
        i = int(np.argmax(learned_pose_scores(pose_features(docks, paint, outline, contour_n))))
        if i not in faced_at:
            faced_at[i] = [f for f in cluster.fragments
                           if facing_geometry(pieces[f][0], contour_n,
                                              _degrees([_compose(_inverse(_deg_to_rad(cluster.poses[f])),
                                                                 in_cluster[i])]))[0][0, 0] >= CLUSTER_FACING_MM]
        out[member] = (_degrees([in_cluster[i]])[0], list(faced_at[i]))
    return out


def _cluster_outline(cluster: Cluster, pieces: Mapping) -> np.ndarray:
    """The cluster's members at their solved poses, merged (:func:`~common.matching.docking.cluster_outline`)."""
    from common.matching.docking import cluster_outline

    return cluster_outline([pieces[f][0] for f in cluster.fragments], [cluster.poses[f] for f in cluster.fragments])


def fit_as_proposal_pose(member_pose, fit, member: str, fragment_a: str) -> tuple[float, float, float]:
    """A next join's ``fit`` (the newcomer's frame in the cluster frame, beside ``member_pose``, the member's) as
    its proposal states a pose: fragment_b in ``fragment_a``'s frame, ``(angle_deg, tx_mm, ty_mm)``."""
    return relative_pose(member_pose, fit) if member == fragment_a else relative_pose(fit, member_pose)


def _deg_to_rad(pose):
    return (math.radians(pose[0]), float(pose[1]), float(pose[2]))


def _degrees(poses) -> np.ndarray:
    """(θ rad, x, y) poses as an (N, 3) array of (angle_deg, tx_mm, ty_mm), the angle wrapped."""
    return np.array([(math.degrees(float(_wrap(p[0]))), p[1], p[2]) for p in poses], float).reshape(-1, 3)


def next_joins(cluster: Cluster, proposals: Iterable, clusters: Iterable[Cluster] = (), *,
               limit: int = 10, pieces: Mapping | None = None) -> list[dict]:
    """The most probable next joins along a cluster's open edges, in the station's order of proposals
    (:data:`common.matching.proposals.ORDER`: mutual proximity, pairs without one last, then probability).

    Parameters
    ----------
    cluster : Cluster
    proposals : iterable of Proposal
        Candidate proposals (e.g. ``ProposalStore.pending(...)``); only pending ones between a member
        and a fragment outside the cluster are kept.
    clusters : iterable of Cluster
        All clusters, to say which one the newcomer already belongs to (or None).
    limit : int
    pieces : mapping fragment -> (contour_mm, paint field or None), optional
        Outlines and paint fields of the members and newcomers: each of the best ``limit`` newcomers is
        then also docked against the whole cluster (:func:`dock_next_joins`), its fit offered where it
        fits a corner.

    Returns
    -------
    list of dict, best first: ``proposal`` (id), ``member``, ``newcomer``, ``probability``, ``mutual``
    (None when the matcher has not ranked the pair in both fragments' lists), ``newcomer_cluster`` (id or
    None), ``pose`` — the newcomer's frame in the cluster frame, ``(angle_deg, tx_mm, ty_mm)``, composed
    from the member's solved pose and the proposal's pose — or None when the proposal has no pose; with
    ``pieces``, also ``fit`` (the pose docked against the whole cluster, or None) and ``faces`` (the members it
    faces there).
    """
    if limit < 1:
        raise ValueError(f"limit must be >= 1, got {limit}")
    members = set(cluster.fragments)
    owner = {f: c.id for c in clusters for f in c.fragments}
    out = []
    for p in proposals:
        if getattr(p, "status", "pending") != "pending":
            continue
        a, b = p.fragment_a, p.fragment_b
        if (a in members) == (b in members):
            continue
        member, newcomer = (a, b) if a in members else (b, a)
        pose = None
        if p.angle_deg is not None:
            xm = _deg_to_rad(cluster.poses[member])
            z = _deg_to_rad((p.angle_deg, p.tx_mm, p.ty_mm))
            xn = _compose(xm, z if member == a else _inverse(z))
            pose = (math.degrees(float(_wrap(xn[0]))), xn[1], xn[2])
        mutual = getattr(p, "mutual", None)
        out.append({"proposal": p.id, "member": member, "newcomer": newcomer, "probability": float(p.probability),
                    "mutual": None if mutual is None else float(mutual), "newcomer_cluster": owner.get(newcomer),
                    "pose": pose, "fit": None, "faces": []})
    out.sort(key=lambda d: order_key(d["mutual"], d["probability"], d["proposal"]))
    out = out[:limit]
    return out if pieces is None else dock_next_joins(cluster, out, pieces)


def dock_key(cluster: Cluster, member: str, newcomer: str) -> tuple:
    """What a newcomer's docking against a cluster depends on: the member, the newcomer and every member's
    solved pose (to 1 µm and 1 µdeg), the key of :func:`dock_next_joins`' cache."""
    return (member, newcomer, tuple((f, *(round(float(v), 6) for v in cluster.poses[f])) for f in sorted(cluster.fragments)))


def dock_next_joins(cluster: Cluster, nexts: list[dict], pieces: Mapping, *,
                    cache: MutableMapping | None = None) -> list[dict]:
    """:func:`next_joins`' entries with each newcomer docked against the whole cluster (:func:`dock_newcomer`): an
    entry gets ``fit`` — that pose, the newcomer's frame in the cluster frame — and ``faces`` where the newcomer
    faces two members or more there, the proposal's member among them (else ``fit`` None).

    The fit is offered beside the proposal's pose, not in its place: in simulated review sessions
    (``tests/bench/bench_review_session.py``, docs/matching.md "Docking against a confirmed cluster") it was
    the right pose less often than the pair's own on RePAIR and about as often on synthetic walls.

    ``pieces`` maps fragment -> (contour_mm, paint field or None); an entry whose newcomer or any member has
    none gets no fit. ``cache`` (keyed by :func:`dock_key`, values ``(pose, faced)``) keeps dockings made
    before, so a caller that shows the same clusters again (the web's reconstruction page) docks each newcomer
    once; an entry found there needs no pieces. A newcomer proposed to several members of the cluster is docked
    against it once (:func:`dock_newcomer_members`), each entry's fit chosen with its own member's paint.
    Returns new dicts; ``nexts`` is not changed.
    """
    cache = {} if cache is None else cache
    todo: dict[str, list[str]] = {}    # newcomer -> the members it is proposed to, not docked before
    if all(f in pieces for f in cluster.fragments):
        for d in nexts:
            if d["newcomer"] in pieces and dock_key(cluster, d["member"], d["newcomer"]) not in cache:
                todo.setdefault(d["newcomer"], []).append(d["member"])
    outline = _cluster_outline(cluster, pieces) if todo else None   # made once per cluster, for all its newcomers
    for newcomer, members in todo.items():    # docked once, whichever members it is proposed to
        for member, (docked, faced) in dock_newcomer_members(cluster, members, newcomer, pieces,
                                                             outline=outline).items():
            cache[dock_key(cluster, member, newcomer)] = (tuple(float(v) for v in docked), list(faced))
    out = []
    for d in nexts:
        d = dict(d, fit=None, faces=[])
        key = dock_key(cluster, d["member"], d["newcomer"])
        if key in cache:
            docked, faced = cache[key]
            # held by two members, one of them the proposal's: the corner pins it (one crack alone does not;
            # a fit away from the member the proposal joins it to is a nest in another corner, never right in
            # the simulated review sessions)
            if len(faced) >= 2 and d["member"] in faced:
                d.update(fit=tuple(docked), faces=list(faced))
        out.append(d)
    return out


# -- composite ---------------------------------------------------------------------------------
def cluster_extent_mm(cluster: Cluster, images: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """(min corner, max corner) in mm of the cluster's fragments' masks at their poses."""
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for f in cluster.fragments:
        img = images[f]
        rr, cc = np.nonzero(img.mask)
        if not len(rr):
            continue
        box = np.array([[cc.min(), rr.min()], [cc.max(), rr.min()], [cc.min(), rr.max()], [cc.max(), rr.max()]],
                       float) * img.pixel_mm
        a, tx, ty = cluster.poses[f]
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        p = box @ np.array([[c, s], [-s, c]]) + (tx, ty)
        lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise ValueError(f"cluster {cluster.id}: no fragment has a non-empty mask")
    return lo, hi


def compose_cluster(cluster: Cluster, images: Mapping, *, dpi: float | None = None, max_side_px: int = 8192,
                    margin_mm: float = 2.0) -> dict:
    """Each fragment's albedo warped into the cluster frame at its solved pose: one picture.

    Parameters
    ----------
    cluster : Cluster
    images : mapping fragment -> RGBNImage
        The front face of every fragment of the cluster (albedo linear RGB, mask, dpi).
    dpi : float, optional
        Output sampling; default the lowest dpi among the fragments (nothing is upsampled), lowered
        further if needed so the longer side stays within ``max_side_px``.
    max_side_px : int
    margin_mm : float
        Border around the fragments.

    Returns
    -------
    dict with ``albedo`` (H, W, 3) float32 linear RGB (mean where fragments overlap), ``alpha``
    (H, W) float32 (1 on a fragment), ``overlap`` (H, W) bool (covered by two or more fragments),
    ``origin_mm`` (cluster-frame position of pixel (0, 0)), ``dpi``, ``pixel_mm``.
    Pixel (col, row) lies at ``origin_mm + (col, row) * pixel_mm`` in the cluster frame.
    """
    missing = [f for f in cluster.fragments if f not in images]
    if missing:
        raise ValueError(f"cluster {cluster.id}: no image for fragment(s) {', '.join(missing)}")
    if dpi is not None and not (np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be a positive number, got {dpi}")
    if max_side_px < 16:
        raise ValueError(f"max_side_px must be >= 16, got {max_side_px}")
    lo, hi = cluster_extent_mm(cluster, images)
    lo, hi = lo - margin_mm, hi + margin_mm
    dpi = float(dpi if dpi is not None else min(images[f].dpi for f in cluster.fragments))
    pixel_mm = 25.4 / dpi
    if (hi - lo).max() / pixel_mm + 1 > max_side_px:
        pixel_mm = float((hi - lo).max() / (max_side_px - 1))
        dpi = 25.4 / pixel_mm
    W, H = (np.floor((hi - lo) / pixel_mm).astype(int) + 1)
    acc = np.zeros((H, W, 3), np.float32)
    weight = np.zeros((H, W), np.float32)
    count = np.zeros((H, W), np.uint8)
    for f in cluster.fragments:
        img = images[f]
        a, tx, ty = cluster.poses[f]
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        k = img.pixel_mm / pixel_mm
        # fragment pixel (col, row) -> canvas pixel: (R (col, row) pixel_mm_f + t - lo) / pixel_mm
        M = np.array([[c * k, -s * k, (tx - lo[0]) / pixel_mm], [s * k, c * k, (ty - lo[1]) / pixel_mm]])
        src_alpha = img.mask.astype(np.float32)
        flags = cv2.INTER_AREA if k < 1 else cv2.INTER_LINEAR
        rgb = cv2.warpAffine(img.albedo * src_alpha[..., None], M, (int(W), int(H)), flags=flags,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        al = cv2.warpAffine(src_alpha, M, (int(W), int(H)), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        acc += rgb
        weight += al
        count += (al > 0.5)
    alpha = np.clip(weight, 0.0, 1.0)
    albedo = np.where(weight[..., None] > 1e-6, acc / np.maximum(weight, 1e-6)[..., None], 0.0).astype(np.float32)
    return {"albedo": albedo, "alpha": alpha.astype(np.float32), "overlap": count >= 2,
            "origin_mm": (float(lo[0]), float(lo[1])), "dpi": dpi, "pixel_mm": pixel_mm}


# -- JSON --------------------------------------------------------------------------------------
def reconstruction_document(clusters: list[Cluster], *, unposed: Iterable = (), next_by_cluster: Mapping | None = None,
                            dpi: Mapping | None = None, composites: Mapping | None = None,
                            sigma_mm: float = SIGMA_MM, sigma_deg: float = SIGMA_DEG,
                            p_value: float = P_VALUE) -> dict:
    """The JSON-ready reconstruction: clusters, poses, joins, loops (schema ``tessera.reconstruction`` v1).

    ``dpi`` maps fragment -> dpi of its front image; ``composites`` maps cluster id -> a dict
    (files, dpi, origin_mm) describing its exported picture; ``next_by_cluster`` cluster id -> the
    :func:`next_joins` list. See ``docs/storage.md``, "Reconstruction JSON".
    """
    from common import __version__

    dpi, composites, next_by_cluster = dict(dpi or {}), dict(composites or {}), dict(next_by_cluster or {})
    out = {"schema": SCHEMA, "version": SCHEMA_VERSION, "software_version": __version__,
           "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "frame": FRAME, "face": "front",
           "noise": {"sigma_mm": sigma_mm, "sigma_deg": sigma_deg, "p_value": p_value,
                     "chi2_bound": float(_chi2.ppf(1.0 - p_value, 3))},
           "unposed_joins": [list(p) for p in unposed], "clusters": []}
    for c in clusters:
        out["clusters"].append({
            "id": c.id, "root": c.root,
            "fragments": [{"fragment": f, "angle_deg": c.poses[f][0], "tx_mm": c.poses[f][1],
                           "ty_mm": c.poses[f][2], "dpi": dpi.get(f)} for f in c.fragments],
            "joins": [{"fragment_a": j.fragment_a, "fragment_b": j.fragment_b, "angle_deg": j.angle_deg,
                       "tx_mm": j.tx_mm, "ty_mm": j.ty_mm, "by": j.by, "time": j.time, "proposal": j.proposal_id,
                       **{f"residual_{k}": v for k, v in c.residuals[j.pair].items()}} for j in c.joins],
            "loops": [{"fragments": lp.fragments, "joins": [list(p) for p in lp.joins],
                       "residual_deg": lp.residual_deg, "residual_mm": lp.residual_mm, "chi2": lp.chi2,
                       "conflicting": lp.conflicting} for lp in c.loops],
            "n_conflicting_loops": len(c.conflicting_loops),
            "blamed": [list(p) for p in c.blamed],
            "solve": {"cost": c.cost, "evaluations": c.iterations, "cpu_s": c.solve_s},
            "next_joins": [{**d, **{k: dict(zip(("angle_deg", "tx_mm", "ty_mm"), d[k])) if d.get(k) else None
                                    for k in ("pose", "fit")}}
                           for d in next_by_cluster.get(c.id, [])],
            "composite": composites.get(c.id)})
    return out


# -- a station's reconstruction ----------------------------------------------------------------
def mask_centre_mm(image) -> tuple[float, float]:
    """Centroid (x, y) in mm of an RGBN image's mask, in the fragment's frame (x = col·pixel_mm)."""
    rr, cc = np.nonzero(image.mask)
    if not len(rr):
        raise ValueError("the image's mask is empty: the fragment has no centre")
    return (float(cc.mean() * image.pixel_mm), float(rr.mean() * image.pixel_mm))


def front_images(store, fragments: Iterable[str]) -> tuple[dict, dict]:
    """The newest front RGBN image of each fragment on storage: ({fragment: image}, {fragment: why missing})."""
    from common.imports.export import latest_faces
    from common.rgbn.image import load_rgbn
    from common.store import ArtifactError

    images, missing = {}, {}
    for f in fragments:
        rel = latest_faces(store, f).get("front")
        if rel is None:
            missing[f] = f"no front RGBN image under fragments/{f}/rgbn"
            continue
        try:
            images[f] = load_rgbn(store, rel)
        except (ArtifactError, OSError, ValueError) as exc:
            missing[f] = f"{rel}: {exc}"
    return images, missing


def front_pieces(store, tables: Iterable[dict], fragments: Iterable[str], *,
                 cache: MutableMapping | None = None) -> tuple[dict, dict]:
    """Each fragment's outline and paint field (front face) from its feature table, as :func:`dock_newcomer`
    takes them: ``({fragment: (contour_mm, paint field or None)}, {fragment: why it has none})``.

    ``tables`` are the proposal store's rows of feature tables (``ProposalStore.fragments(face="front")``);
    ``cache`` (keyed by the table's path and digest) keeps pieces read before.
    """
    from common.features import load_features
    from common.matching.paint import paint_field_from_profile
    from common.store import ArtifactError

    wanted = set(fragments)
    arts = {r["fragment"]: r["artifact"] for r in tables if r["fragment"] in wanted}
    cache = {} if cache is None else cache
    pieces, missing = {}, {}
    for f in sorted(wanted):
        if f not in arts:
            missing[f] = "no feature table in the proposal store"
            continue
        key = (arts[f]["path"], arts[f].get("sha256"))
        if key not in cache:
            try:
                table = load_features(store, arts[f], face="front")
            except (ArtifactError, OSError, ValueError) as exc:   # missing, corrupt, newer: no fit for it
                missing[f] = f"{type(exc).__name__}: {exc}"
                continue
            profile = table.boundary_profile
            cache[key] = (table.contour_mm,
                          None if profile is None else paint_field_from_profile(table.contour_mm, profile))
        pieces[f] = cache[key]
    return pieces, missing


def reconstruct(proposals, *, centres_mm: Mapping | Callable | None = None, dpi: Mapping | None = None,
                sigma_mm: float = SIGMA_MM, sigma_deg: float = SIGMA_DEG, p_value: float = P_VALUE,
                next_limit: int = 10, pieces: Mapping | Callable | None = None) -> dict:
    """Solve a station's confirmed joins: clusters, loops, open edges, the JSON document.

    Parameters
    ----------
    proposals : ProposalStore
        The matcher's database (verdicts with the pose seen; pending proposals for the open edges).
    centres_mm : mapping fragment -> (x, y), or callable(list of fragment ids) -> such a mapping
        Each fragment's centre in its frame (:func:`mask_centre_mm` of its front image); a callable
        is asked only for the fragments that have confirmed joins. Fragments without one are
        anchored at their frame origin.
    dpi : mapping fragment -> dpi, optional
        Written into the document.
    pieces : mapping fragment -> (contour_mm, paint field or None), or callable(list of fragment ids) -> such a
        mapping, optional
        Outlines (e.g. :func:`front_pieces`): each next join's newcomer is then docked against its whole cluster
        (:func:`next_joins`); a callable is asked for the clusters' members and the newcomers only.

    Returns
    -------
    dict: ``clusters`` (list of Cluster), ``unposed`` (confirmed pairs without a pose), ``next``
    (cluster id -> :func:`next_joins`), ``document`` (:func:`reconstruction_document`, without
    composites).
    """
    joins, unposed = confirmed_joins(proposals)
    fragments = sorted({f for j in joins for f in j.pair})
    centres = dict(centres_mm(fragments) if callable(centres_mm) else (centres_mm or {}))
    clusters = solve_pose_graph(joins, sigma_mm=sigma_mm, sigma_deg=sigma_deg, p_value=p_value,
                                centres_mm={f: centres[f] for f in fragments if f in centres})
    pending = []
    for f in fragments:
        pending += proposals.ranked(f, limit=4 * next_limit, status="pending")
    unique = list({p.id: p for p in pending}.values())
    if callable(pieces):
        pieces = pieces(sorted(set(fragments) | {f for p in unique for f in (p.fragment_a, p.fragment_b)}))
    nxt = {c.id: next_joins(c, unique, clusters, limit=next_limit, pieces=pieces) for c in clusters}
    doc = reconstruction_document(clusters, unposed=unposed, next_by_cluster=nxt, dpi=dpi,
                                  sigma_mm=sigma_mm, sigma_deg=sigma_deg, p_value=p_value)
    return {"clusters": clusters, "unposed": unposed, "next": nxt, "document": doc}


def write_composite(composite: dict, png_path, tiff_path=None) -> list:
    """Write a :func:`compose_cluster` picture: 8-bit sRGB PNG and 16-bit sRGB TIFF, alpha = coverage, both
    declaring the composite's dpi."""
    from common.rgbn.io import linear_to_srgb, write_image

    srgb = linear_to_srgb(composite["albedo"])
    dpi = composite.get("dpi")
    out = [write_image(png_path, srgb, bits=8, alpha=composite["alpha"], dpi=dpi)]
    if tiff_path is not None:
        out.append(write_image(tiff_path, srgb, bits=16, alpha=composite["alpha"], dpi=dpi))
    return out
