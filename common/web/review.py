"""What the review page shows: proposals, verdict history and pictures of proposed joins.

Reads the matcher's proposal store (:class:`common.matching.proposals.ProposalStore`, SQLite)
and the fragments' RGBN artifacts; writes nothing (verdicts travel as ``match.verified`` events
and the matcher records them). Pictures: both fragments side by side (at one mm a pixel, so their
sizes compare) and joined at the proposed pose (:func:`common.web.compose.join_at_pose`), in colour (albedo, sRGB) and in relief
(exaggerated shading of the normals, §7.3.5, or a raking light when the renderer is absent).
"""

from __future__ import annotations

import collections
import logging
import os
import sqlite3
import threading
from pathlib import Path
from typing import Mapping

import cv2
import numpy as np

from common.rgbn.image import RGBNImage, load_rgbn
from common.store import Store
from common.web.compose import encode_png, fit_within, join_at_pose, linear_to_srgb8, raking_light, side_by_side

log = logging.getLogger("tessera.web.review")

VIEWS = ("pair-colour", "pair-relief", "joined-colour", "joined-relief")


#: the numbers of a pose (fragment B in fragment A's frame: degrees, mm)
POSE_KEYS = ("angle_deg", "tx_mm", "ty_mm")


def _pose(values) -> dict | None:
    """``{angle_deg, tx_mm, ty_mm}`` as floats, or None when one is missing."""
    if not values or any(values.get(k) is None for k in POSE_KEYS):
        return None
    return {k: float(values[k]) for k in POSE_KEYS}


def proposal_dict(p, latest: Mapping | None = None) -> dict:
    """A :class:`~common.matching.proposals.Proposal` as JSON for the page (evidence left out).

    ``latest``: the pair's latest verdict (``verdict``, ``pose``, ``time``), recorded or sent and not yet
    recorded. A decided proposal stands at the pose kept with that verdict (the pose the person saw or set:
    a confirmation's corrected pose), so ``pose`` — what the pictures show and what a verdict without a new
    correction keeps — is that one; ``proposed_pose`` is the matcher's, ``verdict_pose`` the verdict's (or None).
    """
    proposed = _pose({"angle_deg": p.angle_deg, "tx_mm": p.tx_mm, "ty_mm": p.ty_mm})
    kept = _pose((latest or {}).get("pose"))
    return {"id": int(p.id), "fragment_a": p.fragment_a, "fragment_b": p.fragment_b,
            "probability": float(p.probability), "mutual": None if p.mutual is None else float(p.mutual),
            "status": p.status, "model_version": p.model_version,
            "pose": kept or proposed, "proposed_pose": proposed, "verdict_pose": kept,
            "verdict": (latest or {}).get("verdict"), "alignment": p.alignment, "updated": p.updated}


def relief_picture(image: RGBNImage) -> np.ndarray:
    """Relief rendering of an RGBN image as (H, W, 3) uint8: exaggerated shading (§7.3.5).

    Colour-only images (no normals) get their albedo as grey, so the page still shows the shape.
    """
    if image.normals is None:
        grey = linear_to_srgb8(image.albedo.mean(axis=2))
        return np.repeat(grey[..., None], 3, axis=2)
    try:
        from common.render.shading import exaggerated_shading
    except ImportError:  # renderer not installed on this host: a raking light shows relief too
        return raking_light(image.normals, image.mask)
    shade = np.asarray(exaggerated_shading(image.normals, mask=image.mask), dtype=np.float32)
    if shade.ndim == 2:
        shade = np.repeat(shade[..., None], 3, axis=2)
    out = np.round(np.clip(shade, 0, 1) * 255).astype(np.uint8)
    out[~image.mask] = 0
    return out


def shrink_rgbn(image: RGBNImage, max_side_px: int) -> RGBNImage:
    """An RGBN image scaled down (area averaging) so its longer side is at most ``max_side_px``.

    Normals are averaged and renormalised, the mask resampled by nearest neighbour, the dpi
    scaled with the pixels so physical sizes (and poses in mm) stay right. Never upscales.
    """
    h, w = image.mask.shape
    s = max_side_px / max(h, w)
    if s >= 1.0:
        return image
    size = (max(1, round(w * s)), max(1, round(h * s)))
    albedo = cv2.resize(image.albedo, size, interpolation=cv2.INTER_AREA)
    mask = cv2.resize(image.mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    normals = None
    if image.normals is not None:
        n = cv2.resize(np.nan_to_num(image.normals), size, interpolation=cv2.INTER_AREA)
        norm = np.linalg.norm(n, axis=2, keepdims=True)
        normals = np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), np.array([0, 0, 1], np.float32))
    return RGBNImage(albedo, mask, image.dpi * size[0] / w, normals=normals)


class ReviewData:
    """Proposals, history and pictures for the review page.

    Parameters
    ----------
    db_path : path
        The matcher's proposal database.
    store : Store
        Storage root holding ``fragments/<id>/rgbn/``.
    cache_pictures : int
        Rendered pictures kept in memory (least recently used dropped).
    """

    def __init__(self, db_path: str | os.PathLike, store: Store, *, cache_pictures: int = 64,
                 journal_mode: str = "WAL"):
        self.db_path = Path(db_path)
        self.store = store
        self.journal_mode = journal_mode
        self._lock = threading.RLock()
        self._store = None
        self._cache: collections.OrderedDict = collections.OrderedDict()
        self._cache_lock = threading.Lock()
        self._cache_size = int(cache_pictures)
        # verdicts this process sent that the matcher has not recorded yet: proposal id -> verdict, pose, time
        self._sent: collections.OrderedDict = collections.OrderedDict()

    @classmethod
    def from_config(cls, cfg: Mapping) -> "ReviewData":
        """Database from ``[services.matcher] db`` (default ``<root>/matches/proposals.sqlite``)."""
        from common.matching.proposals import proposals_path

        root = Path(cfg["storage"]["root"])
        matcher = dict(cfg.get("services", {}).get("matcher", {}))
        db = proposals_path(root, matcher.get("db"))
        return cls(db, Store(root, file_locking=cfg["storage"]["file_locking"]),
                   journal_mode=str(matcher.get("journal_mode", "WAL")))

    # -- the database ------------------------------------------------------------------------
    def _db(self):
        """The proposal store, opened read-only once and shared by the server's threads.

        The web server runs each request on a new thread; a connection per thread would leak one
        file per request, and opening a :class:`ProposalStore` per request would take SQLite's
        write lock (it creates its schema) against the matcher. So one read-only connection
        (``mode=ro``, usable from any thread, guarded by ``self._lock``) is bound to the store's
        own query methods.
        """
        from common.matching.proposals import ProposalStore

        db = getattr(self, "_store", None)
        if db is None:
            if not self.db_path.exists():
                return None   # no matcher has run yet: nothing to review
            con = sqlite3.connect(f"file:{self.db_path}?mode=ro", uri=True, check_same_thread=False,
                                  isolation_level=None, timeout=10.0)
            con.row_factory = sqlite3.Row
            db = ProposalStore.__new__(ProposalStore)
            db.path, db._db = self.db_path, con
            self._store = db
        return db

    def _read(self, fn, default):
        with self._lock:
            db = self._db()
            return fn(db) if db is not None else default

    def sent(self, pid: int, verdict: str, pose: Mapping | None, when: float) -> None:
        """Note a verdict this process sent (its ``match.verified``: ``time`` = ``when``) until the matcher
        records it: meanwhile the proposal stands at its pose as if recorded, so a second verdict without a
        new correction keeps it, even while the broker is down."""
        with self._cache_lock:
            self._sent[int(pid)] = {"verdict": verdict, "pose": dict(pose) if pose else None, "time": float(when)}
            self._sent.move_to_end(int(pid))
            while len(self._sent) > 1000:
                self._sent.popitem(last=False)

    def _latest(self, db, p) -> dict | None:
        """The pair's latest verdict: the recorded one, or one sent since that the matcher has not recorded."""
        v = db.latest_verdict(p.fragment_a, p.fragment_b)
        recorded = {"verdict": v.verdict, "pose": v.pose, "time": v.time} if v is not None else None
        with self._cache_lock:
            sent = self._sent.get(int(p.id))
            if sent is not None and recorded is not None and recorded["time"] >= sent["time"]:
                del self._sent[int(p.id)]   # recorded (it carries the message's time), or overtaken
                sent = None
        return sent or recorded

    def _dicts(self, db, proposals) -> list[dict]:
        return [proposal_dict(p, self._latest(db, p)) for p in proposals]

    def pending(self, limit: int = 50) -> list[dict]:
        """Pending proposals, most probable first."""
        return self._read(lambda db: self._dicts(db, db.pending(limit)), [])

    def ranked(self, fragment: str, limit: int = 20) -> list[dict]:
        """Proposals involving ``fragment`` (any status), most probable first."""
        return self._read(lambda db: self._dicts(db, db.ranked(fragment, limit)), [])

    def proposal(self, pid) -> dict | None:
        """One proposal by id, or None (also for an id that is no SQLite integer: a bool, ``1e400``, ``2**70``, or
        no whole number: ``1.9`` is not proposal 1)."""
        if isinstance(pid, bool) or (isinstance(pid, float) and not pid.is_integer()):
            return None
        try:
            pid = int(pid)
        except (TypeError, ValueError, OverflowError):
            return None
        if not 0 <= pid < 2 ** 63:
            return None
        def by_id(db):
            if hasattr(db, "by_id"):
                return db.by_id(pid)
            from common.matching.proposals import _proposal   # no public lookup by id yet
            row = db._db.execute("SELECT * FROM proposals WHERE id=?", (pid,)).fetchone()
            return _proposal(row) if row else None

        def one(db):
            found = by_id(db)
            return self._dicts(db, [found])[0] if found else None

        return self._read(one, None)

    def history(self, limit: int = 100) -> list[dict]:
        """Recorded verdicts, newest first."""
        out = [{"fragment_a": v.fragment_a, "fragment_b": v.fragment_b, "verdict": v.verdict, "by": v.by,
                "time": v.time, "proposal": v.proposal_id, "note": v.note}
               for v in self._read(lambda db: db.verdicts(), [])]
        return out[::-1][:limit]

    def counts(self) -> dict:
        return self._read(lambda db: {s: db.count(s) for s in ("pending", "confirmed", "rejected")},
                          {"pending": 0, "confirmed": 0, "rejected": 0})

    def matched_fragments(self) -> set[str]:
        """Fragments the matcher has taken in."""
        return self._read(lambda db: {f["fragment"] for f in db.fragments()}, set())

    # -- pictures ----------------------------------------------------------------------------
    def rgbn(self, fragment: str, face: str = "front") -> tuple[str, RGBNImage]:
        """(relative path, image) of the newest RGBN image of a fragment's face.

        Raises LookupError if there is none yet.
        """
        folder = self.store.root / "fragments" / fragment / "rgbn"
        files = sorted(folder.glob(f"{face}-*.h5"), key=lambda p: p.stat().st_mtime) if folder.is_dir() else []
        if not files:
            raise LookupError(f"fragment {fragment} has no {face} RGBN image yet")
        rel = f"fragments/{fragment}/rgbn/{files[-1].name}"
        return rel, load_rgbn(self.store, rel)

    def adjusted_pose(self, pid: int, turn_deg: float = 0.0, shift_mm=(0.0, 0.0), *, max_side_px: int = 640) -> dict:
        """The proposal's pose (``pose``: its latest verdict's when decided, else the proposed one) with
        fragment B turned by ``turn_deg`` about its centre and moved by ``shift_mm`` in A's frame (:func:`common.matching.pose.adjusted_pose`): what the review page's
        pose controls show and a verdict then keeps. Raises LookupError when the proposal or its pose
        is missing."""
        from common.matching.pose import adjusted_pose

        prop, centre = self._posed(pid, max_side_px)
        pose = prop["pose"]
        angle, tx, ty = adjusted_pose((pose["angle_deg"], pose["tx_mm"], pose["ty_mm"]), centre,
                                      turn_deg=turn_deg, shift_mm=shift_mm)
        return {"angle_deg": angle, "tx_mm": tx, "ty_mm": ty}

    def alternatives(self, pid: int, *, max_side_px: int = 640) -> list[dict]:
        """The proposal's other candidate poses (``alignment.alternatives``, best first) as the
        adjustments of its pose that reach them (:meth:`adjustments`), what the review page's pose
        controls then show. Raises LookupError when the proposal or its pose is missing."""
        alternatives = ((self.proposal(pid) or {}).get("alignment") or {}).get("alternatives") or []
        return self.adjustments(pid, alternatives, max_side_px=max_side_px)

    def adjustments(self, pid: int, poses, *, max_side_px: int = 640) -> list[dict]:
        """Each of ``poses`` (dicts of angle_deg, tx_mm, ty_mm: B in A's frame) as the adjustment of the
        proposal's pose that reaches it (:func:`common.matching.pose.adjustment_between`):
        ``[{turn_deg, shift_x_mm, shift_y_mm}]``. Raises LookupError when the proposal or its pose is missing."""
        from common.matching.pose import adjustment_between

        prop, centre = self._posed(pid, max_side_px)
        pose = prop["pose"]
        out = []
        for alt in poses:
            turn, sx, sy = adjustment_between((pose["angle_deg"], pose["tx_mm"], pose["ty_mm"]),
                                              (alt["angle_deg"], alt["tx_mm"], alt["ty_mm"]), centre)
            out.append({"turn_deg": turn, "shift_x_mm": sx, "shift_y_mm": sy})
        return out

    def _posed(self, pid: int, max_side_px: int):
        """(the proposal, B's centre in B's frame, mm): what turning B about its centre needs."""
        prop = self.proposal(pid)
        if prop is None:
            raise LookupError(f"no proposal {pid}")
        if prop["pose"] is None:
            raise LookupError(f"proposal {pid} has no proposed pose yet")
        b, _ = self._fragment_picture(prop["fragment_b"], "colour", max(128, max_side_px // 2))
        ys, xs = np.nonzero(b.mask)
        if not len(xs):
            raise LookupError(f"fragment {prop['fragment_b']} has no pixel on its mask")
        return prop, (xs.mean() * b.pixel_mm, ys.mean() * b.pixel_mm)

    def picture(self, pid: int, view: str, *, max_side_px: int = 640, pose: dict | None = None) -> bytes:
        """PNG of a proposal: ``pair-colour``, ``pair-relief``, ``joined-colour`` or ``joined-relief``;
        the joined views at ``pose`` (angle_deg, tx_mm, ty_mm: B in A's frame) when given, else at the
        proposal's ``pose`` (a decided proposal's: the pose kept with its latest verdict).

        Raises LookupError when the proposal, an image or the pose is missing.
        """
        if view not in VIEWS:
            raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
        prop = self.proposal(pid)
        if prop is None:
            raise LookupError(f"no proposal {pid}")
        if pose is not None:
            prop = dict(prop, pose=pose)
        key = (pid, view, max_side_px, prop["pose"] and tuple(prop["pose"].values()))
        with self._cache_lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        kind = view.split("-")[1]
        each = max(128, max_side_px // 2)   # two fragments share every picture
        (a, pa), (b, pb) = (self._fragment_picture(prop["fragment_a"], kind, each),
                            self._fragment_picture(prop["fragment_b"], kind, each))
        if view.startswith("pair"):   # at one mm a pixel: the sizes compare truthfully, whatever each dpi
            tallest = max((pa, a), (pb, b), key=lambda t: t[0].shape[0] * t[1].pixel_mm)[0]
            img = side_by_side([pa, pb], pixel_mm=[a.pixel_mm, b.pixel_mm],
                               height_px=min(max_side_px // 2, tallest.shape[0]))
            img = fit_within(img, max_side_px)
        else:
            if prop["pose"] is None:
                raise LookupError(f"proposal {pid} has no proposed pose yet")
            pose = (prop["pose"]["angle_deg"], prop["pose"]["tx_mm"], prop["pose"]["ty_mm"])
            img = join_at_pose(pa, a.mask, pb, b.mask, pose, a.pixel_mm, pixel_mm_b=b.pixel_mm,
                               max_side_px=max_side_px)
        png = encode_png(img)
        with self._cache_lock:
            self._cache[key] = png
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return png

    def _fragment_picture(self, fragment: str, kind: str, max_side_px: int) -> tuple[RGBNImage, np.ndarray]:
        """(RGBN image, colour or relief picture) of a fragment at display size, cached.

        The image is first shrunk to ``max_side_px`` (the page never shows it larger), which also
        makes the relief rendering — the costly part — several times cheaper.
        """
        key = ("fragment", fragment, kind, max_side_px)
        with self._cache_lock:
            if key in self._cache and self._cache[key][0] == self._newest(fragment):
                self._cache.move_to_end(key)
                return self._cache[key][1]
        rel, image = self.rgbn(fragment)
        image = shrink_rgbn(image, max_side_px)
        value = (image, self._colour(image) if kind == "colour" else relief_picture(image))
        with self._cache_lock:
            self._cache[key] = (rel, value)
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return value

    def _newest(self, fragment: str) -> str | None:
        folder = self.store.root / "fragments" / fragment / "rgbn"
        files = sorted(folder.glob("front-*.h5"), key=lambda p: p.stat().st_mtime) if folder.is_dir() else []
        return f"fragments/{fragment}/rgbn/{files[-1].name}" if files else None

    @staticmethod
    def _colour(image: RGBNImage) -> np.ndarray:
        out = linear_to_srgb8(image.albedo)
        out[~image.mask] = 0
        return out
