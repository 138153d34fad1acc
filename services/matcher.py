"""Matcher service: on ``features.ready`` propose joins; on ``match.verified`` learn and re-rank (§5).

* ``features.ready`` (front face): the feature artifact is recorded in the proposal store, the
  fragment is added to the in-memory index (only its own cues are computed — nothing else is
  recomputed), its joins are proposed by the staged matcher (:mod:`common.matching.index`), stored,
  and returned as ``match.proposed`` events. Back faces are recorded but not matched. Where the
  model docks (stage 3, about a second per fragment at real sizes), this first answer comes from
  stages 1–2½ alone (``stage: "ranked"``, no pose, ~0.1 s) with a ``match.ranked`` event, which is
  routed back to a matcher:
* ``match.ranked``: the fragment's best candidates are docked, and its joins proposed again with
  their poses (``stage: "docked"``), updating every join the first answer proposed; its best
  partners are ranked again first, so every stored pair carries its mutual proximity in both
  fragments' rankings (what a fragment's proposals and the review queue are ordered by).
* ``match.verified``: the verdict is stored (a re-delivered message is ignored), the logistic
  regression is re-fitted on its bootstrap rows plus every verdict's evidence
  (:func:`common.matching.online.refit_with_verdicts`), saved as the next model version
  (pickle-free), all pending proposals are re-scored in the store, and a ``match.refitted`` event
  is returned, which is routed back to a matcher:
* ``match.refitted``: every fragment is ranked again under the new model with the dockings made
  before (:meth:`MatchIndex.rank_all`; skipped when a newer model is current, whose own
  ``match.refitted`` follows), the mutual proximity of every stored pair is brought up to date, and
  the fragments whose best candidates hold pairs never docked, or whose top joins are not all stored,
  or whose best hold a pending join stored without a pose, are returned ``redock_batch`` at a time in
  ``match.reranked`` events, routed back to a matcher:
* ``match.reranked``: each listed fragment's pairs are docked and its joins proposed again, as a new
  fragment's ``match.ranked`` does, so no docking holds the re-rank (skipped, too, when a newer model
  is current).

State lives in the proposal store (SQLite; ``[services.matcher] db``, default
``<root>/matches/proposals.sqlite`` — on an NFS root put it on the matcher host's local disk) and in
artifacts; the index and model in memory are caches re-synchronised at every job, so several matcher
workers on one host, or a restarted one, see the same fragments and the current model. The pairs'
dockings are kept in the proposal store too (its ``dockings`` table, keyed by both fragments' docking
inputs and the docking's version), so a worker docks no pair that another, or its own earlier life,
docked.

Config (``[services.matcher]``, all optional): ``db``, ``journal_mode`` ("WAL"), ``n_candidates``
(100), ``top`` (10 proposals per new fragment), ``check`` (3 aligned), ``bootstrap_fragments`` (60),
``bootstrap_seed`` (0), ``verdict_weight`` (5.0), ``reciprocal`` (10: partners ranked again after a
new fragment's docked answer; 0 leaves their rankings as they were), ``redock_batch`` (8: fragments
per ``match.reranked`` job).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

from common.features import load_features
from common.matching.models import load_model, save_model
from common.matching.online import (VERDICT_WEIGHT, bootstrap_model, evidence_dict, refit_with_verdicts, rerank,
                                    verdict_rows, with_current_ribbon)
from common.matching.index import MatchIndex
from common.matching.pairs import correspondence_columns, fragment_cues
from common.matching.pose import inverse_pose
from common.matching.proposals import Proposal, ProposalStore, ordered_pair, proposals_path
from common.messages import MAX_REDOCK_FRAGMENTS, MessageError, new_message, verdict_of
from common.store import content_key

SERVICE = "matcher"
VERSION = "matcher-1.3"  # 1.1: colour-ribbon stage; 1.2: docking after a first answer (match.ranked);
#                          1.3: the full re-rank after a model update (match.refitted)

#: fragments per ``match.reranked`` job after a model update: each docks ~1 new pair and proposes again
#: (~0.5 s CPU per fragment at real sizes), and a job's ``match.proposed`` events stay within a result frame
REDOCK_BATCH = 8

_STATES: dict = {}


class _State:
    """Per-process caches of one proposal store: the index and the current model."""

    def __init__(self, db: ProposalStore, *, single_fresco: bool = False, fresco_weight: float | None = None):
        self.db = db
        # the dockings are kept in the proposal store: a pair any matcher worker docked is docked once
        self.index = MatchIndex(dockings=db, single_fresco=single_fresco, fresco_weight=fresco_weight)
        self.model = None
        self.seen: dict = {}   # fragment -> sha256 of the indexed feature artifact


def _state(ctx) -> _State:
    cfg = ctx.config or {}
    db_path = proposals_path(ctx.store.root, cfg.get("db"))
    key = (str(ctx.store.root), str(db_path))
    st = _STATES.get(key)
    if st is None:
        st = _STATES[key] = _State(ProposalStore(db_path, journal_mode=str(cfg.get("journal_mode", "WAL"))),
                                   single_fresco=_flag(cfg.get("single_fresco", False), "single_fresco"),
                                   fresco_weight=_weight(cfg.get("fresco_weight"), "fresco_weight"))
    _sync(st, ctx)
    return st


def _weight(value, name: str) -> float | None:
    """A weight setting of ``[services.matcher]``: a number >= 0, or absent (None: the library's default)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
        raise ValueError(f"[services.matcher] {name} must be a number >= 0, got {value!r}")
    return float(value)


def _flag(value, name: str) -> bool:
    """A yes/no setting of ``[services.matcher]``: a TOML boolean (a string such as "false" would read as true)."""
    if not isinstance(value, bool):
        raise ValueError(f"[services.matcher] {name} must be true or false, got {value!r}")
    return value


def _sync(st: _State, ctx) -> None:
    """Bring the caches up to the store: fragments other workers added, the current model."""
    for row in st.db.fragments(face="front"):
        f, art = row["fragment"], row["artifact"]
        if st.seen.get(f) != art["sha256"]:
            table = load_features(ctx.store, art, face="front")
            st.index.add(fragment_cues(table, f), table.contour_mm, table.boundary_profile)
            st.seen[f] = art["sha256"]
    current = st.db.current_model()
    if current is None:
        cfg = ctx.config or {}
        ctx.log.info("no match model yet: training the bootstrap model on a synthetic wall")
        model = bootstrap_model(n_fragments=int(cfg.get("bootstrap_fragments", 60)), seed=int(cfg.get("bootstrap_seed", 0)),
                                progress=lambda f, t: ctx.progress(0.5 * f, f"bootstrap model: {t}"))
        ref = save_model(ctx.store, model, provenance={"stage": SERVICE, "stage_version": VERSION})
        st.db.add_model(model.version, ref.to_dict(), n_train=model.info.get("n_train"), note="bootstrap")
        st.model = model
    elif st.model is None or st.model.version != current["version"]:
        st.model = _with_current_ribbon(load_model(ctx.store, current["artifact"]), st, ctx)


def _with_current_ribbon(model, st: _State, ctx):
    """A stored model whose ribbon calibration was fitted for another ribbon score (an older station) has it fitted
    again on the bootstrap wall and becomes the next model version; the patch classifier and what verdicts taught it
    are kept (:func:`common.matching.online.with_current_ribbon`)."""
    cfg = ctx.config or {}
    renewed = with_current_ribbon(model, n_fragments=int(cfg.get("bootstrap_fragments", 60)),
                                  seed=int(cfg.get("bootstrap_seed", 0)),
                                  progress=lambda f, t: ctx.progress(0.5 * f, f"ribbon calibration: {t}"))
    if renewed is model:
        return model
    ref = save_model(ctx.store, renewed, provenance={"stage": SERVICE, "stage_version": VERSION,
                                                     "previous": model.version})
    st.db.add_model(renewed.version, ref.to_dict(), n_train=renewed.info.get("n_train"),
                    note=f"ribbon calibrated again for {renewed.info['ribbon_definition']}")
    ctx.log.info("model %s: its ribbon calibration %s; calibrated again as %s", model.version,
                 renewed.info["ribbon_recalibrated"], renewed.version)
    return renewed


def handle(job: dict, ctx) -> list[dict]:
    """Route a ``features.ready``, ``match.ranked``, ``match.verified``, ``match.refitted`` or ``match.reranked``
    job; return the events to publish."""
    kind = job.get("type")
    if kind == "features.ready":
        return _on_features(job, ctx)
    if kind == "match.ranked":
        return _on_ranked(job, ctx)
    if kind == "match.verified":
        return _on_verified(job, ctx)
    if kind == "match.refitted":
        return _on_refitted(job, ctx)
    if kind == "match.reranked":
        return _on_reranked(job, ctx)
    raise MessageError("matcher handles features.ready, match.ranked, match.verified, match.refitted and "
                       f"match.reranked, got {kind!r}")


def _on_features(job: dict, ctx) -> list[dict]:
    fragment, face = str(job["fragment"]), str(job.get("face", "front"))
    st = _state(ctx)
    if face != "front":
        st.db.add_fragment(fragment, face, job["artifact"])
        ctx.log.info("fragment %s %s face recorded; only front faces are matched", fragment, face)
        return []
    # read (digest, schema, layout) before recording: a bad artifact rejects this job only. Recorded, it would be
    # read by every later job (_sync) and fail each, and it would replace the fragment's good features
    table = load_features(ctx.store, job["artifact"], face="front")
    st.db.add_fragment(fragment, face, job["artifact"])
    if st.seen.get(fragment) != job["artifact"]["sha256"]:   # indexed here, not read again by _sync
        st.index.add(fragment_cues(table, fragment), table.contour_mm, table.boundary_profile)
        st.seen[fragment] = job["artifact"]["sha256"]
    _sync(st, ctx)  # the fragments other workers added meanwhile
    cfg = ctx.config or {}
    cues = st.index.cues[fragment]
    # docking follows as its own job: the first answer is the fast stages' (module docstring)
    dock_later = st.index.uses_docking(fragment, st.model)
    ctx.progress(0.6, f"proposing joins among {len(st.index)} fragments")
    found = st.index.propose(cues, st.model, n_candidates=int(cfg.get("n_candidates", 100)),
                             top=int(cfg.get("top", 10)), check=int(cfg.get("check", 3)), dock=not dock_later)
    if not dock_later:
        _rank_partners_again(found, st, ctx)
    events = _proposed(fragment, found, st, ctx, "ranked" if dock_later else "docked")
    if dock_later:
        events.append(new_message("match.ranked", fragment=fragment, face=face, artifact=job["artifact"],
                                  model_version=st.model.version, fragments=len(st.index),
                                  proposed=[c.other for c in found]))
    return events


def _on_ranked(job: dict, ctx) -> list[dict]:
    fragment = str(job["fragment"])
    st = _state(ctx)
    if st.seen.get(fragment) != job["artifact"].get("sha256"):
        # newer features replaced the ranked ones: their own features.ready brings their match.ranked
        ctx.log.info("fragment %s: features changed since it was ranked; not docking the old ones", fragment)
        return []
    proposed = [str(o) for o in job.get("proposed") or [] if o in st.index]
    ctx.progress(0.3, f"docking the best candidates of {fragment}")
    return _docked_answer(fragment, proposed, st, ctx)


def _docked_answer(fragment: str, proposed, st: _State, ctx) -> list[dict]:
    """Dock the fragment's best candidates (those docked before are cached), propose its joins again with
    their poses — its top ones and every one of ``proposed`` —, store them and return their events."""
    cfg = ctx.config or {}
    found = st.index.propose(st.index.cues[fragment], st.model, n_candidates=int(cfg.get("n_candidates", 100)),
                             top=int(cfg.get("top", 10)), check=int(cfg.get("check", 3)), also=proposed)
    _rank_partners_again(found, st, ctx)
    return _proposed(fragment, found, st, ctx, "docked")


def _rank_partners_again(found, st: _State, ctx) -> None:
    """Mutual proximity needs each partner's view of the new fragment: the best ``reciprocal``
    (config, default 10) partners whose kept ranking predates it are ranked again
    (:meth:`MatchIndex.rank_again`); then the mutual proximity of the candidates (stored by
    :func:`_proposed`) and of every stored pair of the fragment and of those partners is brought up
    to date."""
    if not found:
        return
    fragment, cfg = found[0].fragment, ctx.config or {}
    ctx.progress(0.7, f"ranking the partners of {fragment} again (mutual proximity)")
    again = st.index.rank_again([c.other for c in found[:int(cfg.get("reciprocal", 10))]], st.model,
                                knowing=fragment, n_candidates=int(cfg.get("n_candidates", 100)))
    for c, m in zip(found, st.index.mutual(fragment, [c.other for c in found])):
        c.mutual = m
    updates = []
    for f in [fragment, *again]:
        others = [p.other(f) for p in st.db.ranked(f, limit=10 ** 6)]
        updates += [(f, o, m) for o, m in zip(others, st.index.mutual(f, others))]
    st.db.set_mutual(updates)


def _proposed(fragment: str, found, st: _State, ctx, stage: str) -> list[dict]:
    """Store ``fragment``'s proposals and return their ``match.proposed`` events (the log names the fragment,
    which ``found`` cannot when it is empty)."""
    columns = correspondence_columns()
    props = [_proposal(c, st, columns) for c in found]
    stored = st.db.upsert(props) if props else []
    if stored:
        ctx.log.info("fragment %s: %d proposal%s, %s (best %.3f)", fragment, len(stored), "" if len(stored) == 1 else "s",
                     stage, stored[0].probability)
    else:
        # say why there is no best: the index holds no other fragment yet, or none could be scored with this one
        # (stage 2 scores a pair only when both fragments have a valid patch: a crumb has none)
        others = len(st.index) - (fragment in st.index)
        why = ("no other fragment indexed yet" if others == 0
               else "the 1 other fragment could not be scored with it" if others == 1
               else f"none of the {others} other fragments could be scored with it")
        ctx.log.info("fragment %s: 0 proposals, %s (%s)", fragment, stage, why)
    return [new_message("match.proposed", stage=stage, **p.to_event_fields()) for p in stored]


def _proposal(c, st: _State, columns) -> Proposal:
    """A stored proposal (fragment_a < fragment_b) from an index candidate (query vs other)."""
    a, b = ordered_pair(c.fragment, c.other)
    qa = st.index.cues[c.fragment].patch_index
    qb = st.index.cues[c.other].patch_index
    # a candidate only the ribbon scored (a fragment without a valid patch) has no patch pair
    patch_q = int(qa[c.patch_a]) if c.patch_a >= 0 else None
    patch_o = int(qb[c.patch_b]) if c.patch_b >= 0 else None
    pose = alignment = None
    if c.alignment is not None:
        pose = (c.alignment.angle_deg, c.alignment.tx_mm, c.alignment.ty_mm)   # other in query frame
        alternatives = list(c.alignment.alternatives)
        if a != c.fragment:   # stored as b in a: invert
            pose = inverse_pose(*pose)
            alternatives = [inverse_pose(*alt) for alt in alternatives]
        # the stored proposal (and its match.proposed) states every pose as fragment_b in fragment_a's
        # frame, the alignment's own and its alternatives too
        alignment = dict(replace(c.alignment, alternatives=tuple(alternatives)).to_dict(),
                         angle_deg=float(pose[0]), tx_mm=float(pose[1]), ty_mm=float(pose[2]))
    ev = evidence_dict(c, columns)
    ev["query"] = c.fragment
    return Proposal(a, b, c.probability, st.model.version, mutual=c.mutual if math.isfinite(c.mutual) else None,
                    patch_a=patch_q if a == c.fragment else patch_o, patch_b=patch_o if a == c.fragment else patch_q,
                    angle_deg=pose[0] if pose else None, tx_mm=pose[1] if pose else None,
                    ty_mm=pose[2] if pose else None, alignment=alignment, evidence=ev)


def _on_verified(job: dict, ctx) -> list[dict]:
    st = _state(ctx)
    verdict = verdict_of(job["verdict"])
    a, b = ordered_pair(job["fragment"], job["other"])
    if st.db.get(a, b) is None and a in st.index and b in st.index:
        # a verdict on a pair the matcher never proposed: score it so the verdict has evidence
        found = st.index.rank(st.index.cues[a], [b], st.model)
        if found:
            st.db.upsert([_proposal(found[0], st, correspondence_columns())])
    # the pose the person set on the review page (other in fragment's frame), when they moved it
    recorded = st.db.record_verdict(job["fragment"], job["other"], verdict, by=job.get("by"), note=job.get("note"),
                                    message_uid=job.get("uid"), when=job.get("time"), pose=job.get("pose"))
    latest = st.db.latest_verdicts()
    learned = verdicts_key(latest)
    if recorded is None:
        # re-delivered: done, unless the job that recorded it was stopped before its model or re-score was made
        if st.model.info.get("verdicts_key") != learned:
            ctx.log.info("verdict %s on %s-%s re-delivered; model %s has not learned it (the job that recorded it "
                         "was stopped): learning now", job.get("uid"), a, b, st.model.version)
        else:
            pending = st.db.pending(limit=10 ** 9)
            if all(p.model_version == st.model.version for p in pending):
                ctx.log.info("verdict %s on %s-%s already recorded (re-delivered)", job.get("uid"), a, b)
                return []
            ctx.log.info("verdict %s on %s-%s re-delivered; model %s learned it but the pending proposals were not "
                         "all re-scored (the job was stopped): re-scoring now", job.get("uid"), a, b, st.model.version)
            return _rescore(st, ctx, pending, previous=str(st.model.info.get("previous", "")), verdicts=len(latest))
    # online learning: re-fit on the bootstrap rows + every pair's latest verdict
    columns = list(st.model.columns)
    rows = []
    for (fa, fb), v in latest.items():
        p = st.db.get(fa, fb)
        if p is not None and p.evidence:
            rows.append(verdict_rows(p.evidence, v, columns))
    if st.model.training is None:
        raise RuntimeError(f"model {st.model.version} carries no training rows to re-fit from")
    base_x, base_y, _ = st.model.training
    ctx.progress(0.3, f"re-fitting on {len(base_y)} bootstrap rows and {len(rows)} verdicts")
    model = refit_with_verdicts(base_x, base_y, rows, previous=st.model,
                                verdict_weight=float((ctx.config or {}).get("verdict_weight", VERDICT_WEIGHT)))
    model.info["verdicts_key"] = learned   # what it learned from: a re-delivered verdict checks it
    ref = save_model(ctx.store, model, provenance={"stage": SERVICE, "stage_version": VERSION,
                                                   "previous": st.model.version, "verdicts": len(rows)})
    st.db.add_model(model.version, ref.to_dict(), n_train=len(base_y), note=f"{len(rows)} verdicts")
    previous, st.model = st.model.version, model
    ctx.log.info("verdict %s on %s-%s: model %s", verdict, a, b, model.version)
    return _rescore(st, ctx, st.db.pending(limit=10 ** 9), previous=previous, verdicts=len(rows))


def verdicts_key(latest: dict) -> str:
    """The verdicts a model learned from (every pair's latest, :meth:`ProposalStore.latest_verdicts`) as a short
    key, stored in the model's ``info``: a re-delivered verdict finds whether its job got as far as the model."""
    return content_key("verdicts", *(f"{a} {b} {v}" for (a, b), v in sorted(latest.items())))


def _rescore(st, ctx, pending: list[Proposal], *, previous: str, verdicts: int) -> list[dict]:
    """The ``pending`` proposals (all of them) re-scored under the current model; the full re-rank follows as a
    job of its own."""
    ctx.progress(0.6, f"re-ranking {len(pending)} pending proposals")
    scored = rerank(st.index, st.model, [(p.fragment_a, p.fragment_b) for p in pending])
    st.db.set_probabilities([(p.id, scored[(p.fragment_a, p.fragment_b)].probability) for p in pending
                             if (p.fragment_a, p.fragment_b) in scored], st.model.version)
    ctx.log.info("model %s: %d pending proposals re-ranked", st.model.version, len(scored))
    return [new_message("match.refitted", model_version=st.model.version, previous=previous, verdicts=verdicts,
                        fragments=len(st.index))]


def _on_refitted(job: dict, ctx) -> list[dict]:
    """The full re-rank after a model update (module docstring): rankings and mutual proximity now, the
    dockings of pairs new to a fragment's best in ``match.reranked`` jobs."""
    st = _state(ctx)
    if job["model_version"] != st.model.version:
        ctx.log.info("model %s is no longer current (%s): its match.refitted re-ranks", job["model_version"],
                     st.model.version)
        return []
    cfg = ctx.config or {}
    batch = redock_batch(cfg)   # before the long pass: a bad setting fails at once, named
    ctx.progress(0.1, f"ranking all {len(st.index)} fragments again under model {st.model.version}")
    undocked = st.index.rank_all(st.model, n_candidates=int(cfg.get("n_candidates", 100)))
    ctx.progress(0.9, "mutual proximity of the stored pairs")
    top, updates, redock = int(cfg.get("top", 10)), [], []
    for f in st.index.rankings:
        stored = st.db.ranked(f, limit=10 ** 6)
        others = [p.other(f) for p in stored]
        updates += [(f, o, m) for o, m in zip(others, st.index.mutual(f, others))]
        best = set(st.index.rankings[f][:top])
        # a join the new model lifts into a fragment's best may have been stored without a pose (it was below
        # the docked best when proposed): proposing the fragment again gives it one, for its review
        unposed = st.model.docking is not None and any(
            p.status == "pending" and p.angle_deg is None and p.other(f) in best for p in stored)
        if f in undocked or best - set(others) or unposed:
            redock.append(f)
    st.db.set_mutual(updates)
    ctx.log.info("model %s: %d fragments ranked again; %d to dock and propose again (%d pairs never docked)",
                 st.model.version, len(st.index.rankings), len(redock), sum(len(v) for v in undocked.values()))
    return [new_message("match.reranked", model_version=st.model.version, redock=redock[i:i + batch],
                        fragments=len(st.index)) for i in range(0, len(redock), batch)]


def redock_batch(cfg) -> int:
    """``[services.matcher] redock_batch``: fragments per ``match.reranked`` event, 1 to
    :data:`~common.messages.MAX_REDOCK_FRAGMENTS` (a larger batch would make every event invalid, and each
    re-rank job's events refused as if its input were bad)."""
    batch = cfg.get("redock_batch", REDOCK_BATCH)
    if isinstance(batch, bool) or not isinstance(batch, int) or not 1 <= batch <= MAX_REDOCK_FRAGMENTS:
        raise ValueError(f"[services.matcher] redock_batch must be an integer from 1 to {MAX_REDOCK_FRAGMENTS}, "
                         f"got {batch!r}")
    return batch


def _on_reranked(job: dict, ctx) -> list[dict]:
    """The follow-up of a full re-rank: each listed fragment docked and proposed again (its pending joins
    updated too), as a new fragment's ``match.ranked`` job does."""
    st = _state(ctx)
    if job["model_version"] != st.model.version:
        ctx.log.info("model %s is no longer current (%s): its own re-rank docks", job["model_version"],
                     st.model.version)
        return []
    fragments = [str(f) for f in job["redock"] if f in st.index]
    events = []
    for i, f in enumerate(fragments):
        ctx.progress(i / len(fragments), f"docking the best candidates of {f} ({i + 1}/{len(fragments)})")
        pending = [p.other(f) for p in st.db.ranked(f, limit=10 ** 6, status="pending") if p.other(f) in st.index]
        events += _docked_answer(f, pending, st, ctx)
    return events
