"""Pose graph of confirmed joins against a synthetic wall's ground truth (common/matching/reconstruction.py)."""

import json
import math

import numpy as np
import pytest

from common.matching.reconstruction import (Join, closure_loops, compose_cluster, confirmed_joins, find_clusters,
                                            front_images, mask_centre_mm, next_joins, reconstruct,
                                            reconstruction_document, relative_pose, solve_pose_graph, write_composite)

NOISE_MM, NOISE_DEG = 0.3, 0.3


def _apply(pose, p):
    a = math.radians(pose[0])
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return np.asarray(p, float) @ R.T + np.asarray(pose[1:], float)


@pytest.fixture(scope="module")
def wall150():
    """150 delivered fragments (pose-only: no images), their centres and true joins with bounded noise."""
    from common.synth.wall import generate_wall

    wall = generate_wall(150, seed=3, dpi=20, keep_images=False, surfaces=False, colour_only=True)
    byid = {f.id: f for f in wall.fragments}
    centres = {f.id: tuple(f.contour_mm.mean(axis=0)) for f in wall.fragments}
    return wall, byid, centres


def _noisy_joins(wall, byid, centres, seed=0):
    """True joins from the generator's poses; each turned by ≤ 0.3° about B's centre and shifted ≤ 0.3 mm per axis."""
    rng = np.random.default_rng(seed)
    joins = []
    for a, b, _ in wall.adjacency:
        z = relative_pose(byid[a].pose, byid[b].pose)
        c = _apply(z, [centres[b]])[0]               # B's centre in A's frame
        e = math.radians(rng.uniform(-NOISE_DEG, NOISE_DEG))
        R = np.array([[math.cos(e), -math.sin(e)], [math.sin(e), math.cos(e)]])
        t = R @ (np.array(z[1:]) - c) + c + rng.uniform(-NOISE_MM, NOISE_MM, 2)
        joins.append(Join(a, b, z[0] + math.degrees(e), float(t[0]), float(t[1])))
    return joins


def _errors(cluster, byid, centres):
    """Per piece: centre error (mm) and angle error (deg) after the best rigid fit of the cluster to the truth."""
    root = byid[cluster.root]
    truth = {f: relative_pose(root.pose, byid[f].pose) for f in cluster.fragments}
    A = np.array([_apply(truth[f], [centres[f]])[0] for f in cluster.fragments])
    B = np.array([_apply(cluster.poses[f], [centres[f]])[0] for f in cluster.fragments])
    ma, mb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((B - mb).T @ (A - ma))
    R = (U @ Vt).T
    if np.linalg.det(R) < 0:      # a reflection is no rigid motion of the wall
        raise AssertionError("rigid fit found a reflection")
    rot = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    mm = np.linalg.norm((B - mb) @ R.T + ma - A, axis=1)
    deg = np.array([abs((cluster.poses[f][0] + rot - truth[f][0] + 180.0) % 360.0 - 180.0) for f in cluster.fragments])
    return mm, deg


def test_wall_of_150_true_joins_solves_every_piece_within_1mm_1deg(wall150):
    wall, byid, centres = wall150
    joins = _noisy_joins(wall, byid, centres)
    clusters = solve_pose_graph(joins, centres_mm=centres)
    placed = {f for c in clusters for f in c.fragments}
    # every non-spurious fragment with a true neighbour is placed, in as many clusters as the truth has
    assert placed == {f for a, b, _ in wall.adjacency for f in (a, b)}
    assert [sorted(c.fragments) for c in clusters] == find_clusters(joins)
    assert sum(len(c.fragments) for c in clusters) > 100
    for c in clusters:
        mm, deg = _errors(c, byid, centres)
        assert mm.max() <= 1.0, (c.id, mm.max())
        assert deg.max() <= 1.0, (c.id, deg.max())
        # consistent joins: no loop is flagged, no join given up
        assert c.loops and not c.conflicting_loops
        assert not any(r["suspect"] for r in c.residuals.values())
    # the solve improves on the spanning-tree initialisation it starts from
    tree = solve_pose_graph(joins, centres_mm=centres, refine=False)
    assert _errors(tree[0], byid, centres)[0].max() > _errors(clusters[0], byid, centres)[0].max()


def test_wrong_join_makes_a_conflicting_loop_and_is_given_up(wall150):
    wall, byid, centres = wall150
    joins = _noisy_joins(wall, byid, centres)
    cluster = solve_pose_graph(joins, centres_mm=centres)[0]
    members = cluster.fragments
    # a wrong confirmed join: two pieces of the cluster that are not neighbours, at a plausible pose
    # (a real neighbour's join pose reused)
    a, b = next((x, y) for x in members for y in members if x < y and not wall.is_neighbour(x, y)
                and not set(wall.neighbours(x)) & set(wall.neighbours(y)))
    wrong = Join(a, b, joins[0].angle_deg, joins[0].tx_mm, joins[0].ty_mm)
    loops = closure_loops(joins + [wrong], centres_mm=centres)
    bad = [lp for lp in loops if lp.conflicting]
    assert bad, "the wrong join closed no conflicting loop"
    assert all((a, b) in lp.joins for lp in bad)           # every flagged loop runs through the wrong join
    assert bad[0].residual_mm > 5 or bad[0].residual_deg > 5
    solved = solve_pose_graph(joins + [wrong], centres_mm=centres)[0]
    assert solved.blamed == [(a, b)]
    assert [p for p, r in solved.residuals.items() if r["suspect"]] == [(a, b)]
    # the rest of the wall stays where the true joins put it
    mm, deg = _errors(solved, byid, centres)
    assert mm.max() <= 1.0 and deg.max() <= 1.0


def test_true_join_with_wrong_angle_is_flagged(wall150):
    wall, byid, centres = wall150
    joins = _noisy_joins(wall, byid, centres)
    loops = closure_loops(joins, centres_mm=centres)
    in_loop = loops[0].joins[0]
    k = next(i for i, j in enumerate(joins) if j.pair == in_loop)
    j = joins[k]
    joins[k] = Join(j.fragment_a, j.fragment_b, j.angle_deg + 8.0, j.tx_mm, j.ty_mm)
    flagged = [lp for lp in closure_loops(joins, centres_mm=centres) if lp.conflicting]
    assert flagged and all(in_loop in lp.joins for lp in flagged)


def test_loop_residual_is_the_composed_error():
    # a triangle whose third join is 2 mm off along x in a's frame, and a square that closes
    tri = [Join("a", "b", 90, 10, 0), Join("b", "c", 45, 10, 0), Join("a", "c", 135, 12, 10)]
    (lp,) = closure_loops(tri, sigma_mm=0.2, sigma_deg=0.1)
    assert lp.residual_mm == pytest.approx(2.0, abs=1e-9)
    assert lp.residual_deg == pytest.approx(0.0, abs=1e-9)
    assert lp.conflicting and sorted(lp.fragments) == ["a", "b", "c"]
    (lp,) = closure_loops(tri, sigma_mm=5.0, sigma_deg=5.0)
    assert not lp.conflicting
    sq = [Join("p", "q", 90, 10, 0), Join("q", "r", 90, 10, 0), Join("r", "s", 90, 10, 0), Join("p", "s", -90, 0, 10)]
    (lp,) = closure_loops(sq)
    assert lp.residual_mm < 1e-9 and lp.residual_deg < 1e-9 and len(lp.fragments) == 4


def test_the_join_on_most_conflicting_loops_then_the_latest_is_blamed():
    from common.matching.reconstruction import blame_joins

    # a triangle that does not close: every join is on the one loop; the one confirmed last is blamed
    tri = [Join("a", "b", 0, 10, 0, time=1.0), Join("a", "c", 0, 10, 10, time=3.0), Join("b", "c", 0, 15, 10, time=2.0)]
    assert blame_joins(tri, closure_loops(tri)) == [("a", "c")]
    # two triangles sharing a wrong join b-c: it lies on both conflicting loops, whatever its time
    two = [Join("a", "b", 0, 10, 0, time=5.0), Join("a", "c", 0, 10, 10, time=6.0), Join("b", "c", 0, 20, -5, time=1.0),
           Join("b", "d", 0, 10, 0, time=7.0), Join("c", "d", 0, 10, -10, time=8.0)]
    loops = closure_loops(two)
    assert sum(lp.conflicting for lp in loops) == 2
    assert blame_joins(two, loops) == [("b", "c")]
    assert blame_joins(two, [lp for lp in loops if not lp.conflicting]) == []


def test_separate_clusters_have_their_own_frames():
    joins = [Join("b", "c", 30, 5, 1), Join("x", "y", -60, 3, 4), Join("c", "d", 0, 7, 0)]
    clusters = solve_pose_graph(joins)
    assert [c.id for c in clusters] == ["C:b", "C:x"]
    assert clusters[0].poses["b"] == (0.0, 0.0, 0.0)
    assert clusters[0].poses["d"] == pytest.approx((30.0, 5 + 7 * math.cos(math.radians(30)),
                                                    1 + 7 * math.sin(math.radians(30))))
    assert clusters[1].poses["y"] == pytest.approx((-60.0, 3.0, 4.0))
    assert clusters[1].loops == []


@pytest.mark.parametrize("joins, match", [
    ([Join("a", "a", 0, 0, 0)], "itself"),
    ([Join("a", "b", 0, 0, 0), Join("b", "a", 0, 1, 0)], "two joins"),
    ([Join("a", "b", 0, float("nan"), 0)], "non-finite"),
])
def test_bad_joins_are_refused(joins, match):
    with pytest.raises(ValueError, match=match):
        solve_pose_graph(joins)


def test_bad_noise_model_is_refused():
    with pytest.raises(ValueError, match="sigma_mm"):
        solve_pose_graph([Join("a", "b", 0, 1, 0)], sigma_mm=0)
    with pytest.raises(ValueError, match="loss"):
        solve_pose_graph([Join("a", "b", 0, 1, 0)], loss="l7")
    with pytest.raises(ValueError, match="centres_mm"):
        solve_pose_graph([Join("a", "b", 0, 1, 0)], centres_mm={"b": (1.0,)})


def _proposal_store(tmp_path, wall, byid):
    from common.matching.proposals import Proposal, ProposalStore, ordered_pair

    db = ProposalStore(tmp_path / "proposals.sqlite")
    props = []
    for i, f in enumerate(wall.fragments):
        for g in wall.fragments[i + 1:]:
            a, b = ordered_pair(f.id, g.id)
            if byid[a].pose is None or byid[b].pose is None:
                continue
            z = relative_pose(byid[a].pose, byid[b].pose)
            props.append(Proposal(a, b, 0.9 if wall.is_neighbour(a, b) else 0.1, "m1",
                                  angle_deg=z[0], tx_mm=z[1], ty_mm=z[2]))
    db.upsert(props)
    return db


def test_confirmed_joins_keep_the_pose_the_person_saw(tmp_path):
    from common.matching.proposals import Proposal

    from common.matching.proposals import ProposalStore

    db = ProposalStore(tmp_path / "p.sqlite")
    db.upsert([Proposal("a", "b", 0.9, "m1", angle_deg=10, tx_mm=1, ty_mm=2),
               Proposal("b", "c", 0.8, "m1", angle_deg=20, tx_mm=3, ty_mm=4),
               Proposal("c", "d", 0.7, "m1")])
    db.record_verdict("a", "b", "confirmed")
    db.record_verdict("b", "c", "confirmed")
    db.record_verdict("b", "c", "rejected")        # changed their mind
    db.record_verdict("c", "d", "confirmed")       # no pose was ever proposed
    # a later re-rank moves the proposal's pose: the join keeps what was confirmed
    db.upsert([Proposal("a", "b", 0.95, "m2", angle_deg=99, tx_mm=9, ty_mm=9)])
    joins, unposed = confirmed_joins(db)
    assert [(j.pair, j.angle_deg, j.tx_mm, j.ty_mm) for j in joins] == [(("a", "b"), 10.0, 1.0, 2.0)]
    assert unposed == [("c", "d")]


def test_next_joins_place_the_newcomer_where_the_truth_has_it(tmp_path):
    from common.synth.wall import generate_wall

    wall = generate_wall(12, seed=4, dpi=20, keep_images=False, surfaces=False, colour_only=True,
                         missing_fraction=0.0, spurious_fraction=0.0)
    byid = {f.id: f for f in wall.fragments}
    db = _proposal_store(tmp_path, wall, byid)
    a, b, _ = wall.adjacency[0]
    db.record_verdict(a, b, "confirmed")
    cluster = solve_pose_graph(confirmed_joins(db)[0])[0]
    nxt = next_joins(cluster, db.pending(1000), [cluster], limit=50)
    members = {a, b}
    outside = {x for p in db.pending(1000) for x in (p.fragment_a, p.fragment_b)
               if (p.fragment_a in members) != (p.fragment_b in members)} - members
    assert {d["newcomer"] for d in nxt} == outside
    assert [d["probability"] for d in nxt] == sorted((d["probability"] for d in nxt), reverse=True)
    assert all(d["member"] in members and d["newcomer_cluster"] is None for d in nxt)
    top = nxt[0]
    assert wall.is_neighbour(top["member"], top["newcomer"])
    truth = relative_pose(byid[cluster.root].pose, byid[top["newcomer"]].pose)
    assert (top["pose"][0] - truth[0] + 180) % 360 - 180 == pytest.approx(0, abs=1e-6)
    assert top["pose"][1:] == pytest.approx(truth[1:], abs=1e-6)


def test_composite_puts_each_fragments_albedo_at_its_pose_and_exports(tmp_path):
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from common.synth.wall import generate_wall

    wall = generate_wall(6, seed=2, dpi=40, surfaces=False, missing_fraction=0.0, spurious_fraction=0.0)
    byid = {f.id: f for f in wall.fragments}
    store = Store(tmp_path / "store")
    for f in wall.fragments:
        save_rgbn(store, f"fragments/{f.id}/rgbn/front-{f.id[-3:]}.h5", f.rgbn)
    db = _proposal_store(tmp_path, wall, byid)
    for a, b, _ in wall.adjacency:
        db.record_verdict(a, b, "confirmed")
    images, missing = front_images(store, [f.id for f in wall.fragments])
    assert not missing
    asked = []
    rec = reconstruct(db, centres_mm=lambda ids: asked.extend(ids) or {f: mask_centre_mm(images[f]) for f in ids},
                      dpi={f: images[f].dpi for f in images})
    assert sorted(asked) == sorted({f for a, b, _ in wall.adjacency for f in (a, b)}) and not rec["unposed"]
    rec["images"] = images
    cluster = rec["clusters"][0]
    comp = compose_cluster(cluster, rec["images"])
    px = comp["pixel_mm"]
    assert comp["dpi"] == pytest.approx(40.0)
    # interior pixels of every fragment land where its solved pose puts them, with their own colour
    rng = np.random.default_rng(0)
    from scipy import ndimage
    for f in cluster.fragments:
        img = rec["images"][f]
        inner = ndimage.binary_erosion(img.mask, iterations=2)
        rr, cc = np.nonzero(inner)
        pick = rng.choice(len(rr), size=min(40, len(rr)), replace=False)
        pts = _apply(cluster.poses[f], np.column_stack([cc[pick], rr[pick]]) * img.pixel_mm)
        uv = np.round((pts - comp["origin_mm"]) / px).astype(int)
        got = comp["albedo"][uv[:, 1], uv[:, 0]]
        want = img.albedo[rr[pick], cc[pick]]
        assert np.median(np.abs(got - want)) < 0.03, f
        assert (comp["alpha"][uv[:, 1], uv[:, 0]] > 0.99).all()
    # true joins do not overlap; the covered area is the fragments' area
    area = sum(rec["images"][f].mask.sum() * rec["images"][f].pixel_mm ** 2 for f in cluster.fragments)
    assert comp["alpha"].sum() * px ** 2 == pytest.approx(area, rel=0.03)
    assert comp["overlap"].mean() < 0.01
    # the composite is the wall: the cluster frame is the root's, so the true wall position follows
    png, tif = write_composite(comp, tmp_path / "c.png", tmp_path / "c.tif")
    import cv2
    import tifffile
    p = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    t = tifffile.imread(tif)
    assert p.dtype == np.uint8 and p.shape == comp["albedo"].shape[:2] + (4,)
    assert t.dtype == np.uint16 and t.shape == p.shape
    assert np.abs(t[..., 3].astype(float) / 65535 - comp["alpha"]).max() < 1e-4
    doc = json.loads(json.dumps(rec["document"]))
    assert doc["schema"] == "tessera.reconstruction" and doc["version"] == 1
    poses = {d["fragment"]: (d["angle_deg"], d["tx_mm"], d["ty_mm"]) for d in doc["clusters"][0]["fragments"]}
    root = byid[cluster.root]
    for f, pose in poses.items():
        truth = relative_pose(root.pose, byid[f].pose)
        assert (pose[0] - truth[0] + 180) % 360 - 180 == pytest.approx(0, abs=1e-4)
        assert pose[1:] == pytest.approx(truth[1:], abs=1e-4)


def test_composite_without_an_image_names_the_fragment():
    cluster = solve_pose_graph([Join("a", "b", 0, 5, 0)])[0]
    with pytest.raises(ValueError, match="b"):
        compose_cluster(cluster, {"a": None})


def test_document_lists_loops_and_flags(wall150):
    wall, byid, centres = wall150
    joins = _noisy_joins(wall, byid, centres)[:60]
    clusters = solve_pose_graph(joins, centres_mm=centres)
    doc = json.loads(json.dumps(reconstruction_document(clusters, unposed=[("x", "y")])))
    assert doc["unposed_joins"] == [["x", "y"]]
    assert sum(len(c["fragments"]) for c in doc["clusters"]) == len({f for j in joins for f in j.pair})
    assert sum(len(c["loops"]) for c in doc["clusters"]) == sum(len(c.loops) for c in clusters)
    assert doc["noise"]["chi2_bound"] == pytest.approx(21.108, abs=1e-3)


def _confirmed_station(tmp_path):
    """A six-fragment wall stored as a station's RGBN faces, every true join proposed and confirmed."""
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from common.synth.wall import generate_wall

    wall = generate_wall(6, seed=2, dpi=30, surfaces=False, missing_fraction=0.0, spurious_fraction=0.0)
    byid = {f.id: f for f in wall.fragments}
    store = Store(tmp_path / "store")
    for f in wall.fragments:
        save_rgbn(store, f"fragments/{f.id}/rgbn/front-{f.id[-3:]}.h5", f.rgbn)
    db = _proposal_store(tmp_path / "store" / "matches", wall, byid)
    for a, b, _ in wall.adjacency:
        db.record_verdict(a, b, "confirmed")
    return wall, byid, db


def test_cli_writes_composites_and_poses_and_names_a_conflict(tmp_path, capsys):
    import tifffile

    from services.cli import main

    wall, byid, db = _confirmed_station(tmp_path)
    out = tmp_path / "out"
    assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out)]) == 0
    doc = json.loads((out / "reconstruction.json").read_text())
    (c,) = doc["clusters"]
    assert {d["fragment"] for d in c["fragments"]} == set(byid)
    assert c["composite"]["dpi"] == pytest.approx(30.0)
    assert tifffile.imread(out / c["composite"]["tiff"]).dtype == np.uint16
    assert (out / c["composite"]["png"]).is_file() and c["n_conflicting_loops"] == 0
    # a wrong confirmed join inside the cluster: a conflicting loop, exit 1, named on stderr
    loops = closure_loops(confirmed_joins(db)[0])
    assert loops, "the test wall needs a loop"
    a, b = loops[0].joins[0]
    db._db.execute("UPDATE proposals SET angle_deg = angle_deg + 30 WHERE fragment_a=? AND fragment_b=?", (a, b))
    db.record_verdict(a, b, "confirmed")
    capsys.readouterr()
    assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out), "--json-only"]) == 1
    assert "conflicting loop" in capsys.readouterr().err
    assert json.loads((out / "reconstruction.json").read_text())["clusters"][0]["n_conflicting_loops"] >= 1


def test_cli_writes_strict_json_an_undefined_figure_as_null(tmp_path, monkeypatch):
    """reconstruction.json was written by json.dumps: a NaN or infinite figure came out as bare ``NaN`` /
    ``Infinity``, which jq and a browser's JSON.parse refuse; it is null, as the web's copy of the document."""
    from common.matching import reconstruction as rc
    from services.cli import main

    wall, byid, db = _confirmed_station(tmp_path)
    real = rc.reconstruct

    def undefined(*args, **kwargs):   # figures the document may hold undefined (no path gives one today)
        rec = real(*args, **kwargs)
        c = rec["document"]["clusters"][0]
        c["solve"]["cost"], c["joins"][0]["residual_mm"] = float("inf"), float("nan")
        c["fragments"][0]["dpi"] = float("nan")
        return rec
    monkeypatch.setattr(rc, "reconstruct", undefined)
    out = tmp_path / "out"
    assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out), "--json-only"]) == 0

    def refuse(name):
        raise AssertionError(f"{name} is not JSON")
    (c,) = json.loads((out / "reconstruction.json").read_text(), parse_constant=refuse)["clusters"]
    assert c["solve"]["cost"] is None and c["joins"][0]["residual_mm"] is None and c["fragments"][0]["dpi"] is None
    assert {d["fragment"] for d in c["fragments"]} == set(byid)    # the rest as it was
    assert all(isinstance(d["tx_mm"], float) for d in c["fragments"])


@pytest.mark.parametrize("full", ["before", "while"])
@pytest.mark.parametrize("json_only", [False, True])
def test_cli_on_a_full_disk_names_the_file_and_keeps_the_older_output(tmp_path, monkeypatch, capsys, full, json_only):
    """reconstruct wrote its JSON through its own temporary file and its pictures straight in place, with no
    free-space check: a full disk went unnoticed or left a truncated picture where a good one was. Every file
    goes through common.store.write_file now: the free space checked first (``before``), a disk filled during
    the write (``while``, ENOSPC) refused too; exit 1 naming the file, the older output as it was."""
    import collections
    import errno
    import os
    import shutil
    import stat

    import common.store
    from services.cli import main

    _confirmed_station(tmp_path)
    out = tmp_path / "out"
    argv = ["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out)] + (["--json-only"] if json_only else [])
    assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out)]) == 0
    umask = os.umask(0)
    os.umask(umask)
    older = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {n.rsplit(".", 1)[1] for n in older} == {"json", "png", "tif"}
    assert {n: stat.S_IMODE((out / n).stat().st_mode) for n in older} == {n: 0o666 & ~umask for n in older}
    capsys.readouterr()
    if full == "before":
        usage = collections.namedtuple("usage", "total used free")
        monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 ** 12, 10 ** 12 - 1000, 1000))
    else:
        def half_then_enospc(path, data):   # the disk fills half-way through the file
            with open(path, "wb") as fh:
                fh.write(data[:len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        monkeypatch.setattr(common.store, "_write_bytes", half_then_enospc)
    assert main(argv) == 1
    err = capsys.readouterr().err
    first = out / ("reconstruction.json" if json_only else next(n for n in sorted(older) if n.endswith(".png")))
    said = {"before": f"storage full: {first} needs ", "while": f"storage full: cannot write {first} ("}[full]
    assert f"tessera reconstruct: {said}" in err and f"{out / 'reconstruction.json'} not updated" in err, err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == older      # nothing half-written, nothing left over


def test_cli_without_a_database_says_so(tmp_path, capsys):
    from services.cli import main

    (tmp_path / "store").mkdir()
    assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(tmp_path / "o")]) == 2
    assert "no proposal database" in capsys.readouterr().err


def test_next_joins_come_in_the_review_queues_order():
    """Mutual proximity first (the station's order of proposals, ProposalStore.ORDER), pairs the
    matcher has not ranked both ways last, probability breaking ties."""
    from types import SimpleNamespace

    from common.matching.reconstruction import Cluster

    cluster = Cluster(id="C:A", root="A", fragments=["A", "B"], poses={"A": (0.0, 0.0, 0.0), "B": (0.0, 10.0, 0.0)},
                      joins=[Join("A", "B", 0.0, 10.0, 0.0)])

    def prop(pid, other, probability, mutual):
        return SimpleNamespace(id=pid, fragment_a="A", fragment_b=other, probability=probability, mutual=mutual,
                               status="pending", angle_deg=None, tx_mm=None, ty_mm=None)

    props = [prop(1, "C", 0.99, None), prop(2, "D", 0.40, 0.95), prop(3, "E", 0.90, 0.60), prop(4, "F", 0.95, 0.60),
             prop(5, "G", 0.10, None)]
    got = next_joins(cluster, props, [cluster])
    assert [d["newcomer"] for d in got] == ["D", "F", "E", "C", "G"]
    assert got[0]["mutual"] == 0.95 and got[3]["mutual"] is None


def _broken_square(labels, lost_mm=1.5, cell=0.25, side=60.0):
    """Pieces of a ``side`` mm square broken along wiggly cracks: ``labels(x, y)`` (mm grids) names each point's
    piece; ``lost_mm`` of material is lost on either side of every crack. Returns {piece: outline (K, 2) mm in the
    square's frame}."""
    import cv2
    from scipy import ndimage as ndi

    n = int(side / cell)
    y, x = (np.mgrid[0:n, 0:n] + 0.5) * cell
    lab = labels(x, y)
    out = {}
    for k in np.unique(lab):
        inside = lab == k
        keep = ndi.distance_transform_edt(inside) * cell > lost_mm    # the material along the cracks is lost
        found, _ = cv2.findContours(keep.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        out[str(k)] = max(found, key=cv2.contourArea)[:, 0, :].astype(float) * cell
    return out


def _framed(outlines, poses):
    """Each outline moved into a frame of its own: ``pose`` maps that frame into the square's."""
    out = {}
    for k, c in outlines.items():
        a = math.radians(poses[k][0])
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        out[k] = (c - np.asarray(poses[k][1:])) @ R                     # R^T (p - t), row vectors
    return out


def _corner(x, y):
    """A square's labels: 0 the left half, 1 and 2 the right half's top and bottom, wiggly cracks."""
    right = x > 30 + 2.0 * np.sin(y / 6.0)
    low = y > 30 + 2.0 * np.sin(x / 5.0 + 1.0)
    return np.where(~right, 0, np.where(low, 2, 1))


def test_a_newcomer_in_a_corner_of_the_cluster_is_docked_against_the_whole_cluster():
    """Three pieces of a square: A the left half, B and C the right half's top and bottom, wiggly cracks with
    1.5 mm lost on each side. With A and B confirmed, C fits the corner they make: docked against the cluster
    it lands within 3 degrees and 3 mm of the truth (the docking's grid: 4 degree steps refined to 1, 1.5 mm
    cells; right, as tessera evaluate counts it, is 5 and 5), though the A-C proposal had it slid 15 mm down
    the crack, and it faces both members there: that fit is offered beside the proposal's pose."""
    from types import SimpleNamespace

    from common.matching.reconstruction import Cluster, dock_newcomer, dock_next_joins

    truth = {"0": (0.0, 0.0, 0.0), "1": (35.0, 40.0, -5.0), "2": (-110.0, 50.0, 55.0)}   # each frame in the square's
    outlines = _framed(_broken_square(_corner), truth)
    cluster = Cluster(id="C:0", root="0", fragments=["0", "1"], poses={"0": truth["0"], "1": truth["1"]},
                      joins=[Join("0", "1", *relative_pose(truth["0"], truth["1"]))])
    pieces = {k: (c, None) for k, c in outlines.items()}
    slid = relative_pose(truth["0"], (truth["2"][0], truth["2"][1], truth["2"][2] + 15.0))   # 15 mm down the crack
    prop = SimpleNamespace(id=1, fragment_a="0", fragment_b="2", probability=0.9, mutual=0.9, status="pending",
                           angle_deg=slid[0], tx_mm=slid[1], ty_mm=slid[2])
    plain = next_joins(cluster, [prop], [cluster])[0]
    docked = next_joins(cluster, [prop], [cluster], pieces=pieces)[0]
    assert plain["fit"] is None and plain["pose"][2] == pytest.approx(truth["2"][2] + 15.0, abs=1e-6)
    assert docked["pose"] == plain["pose"] and sorted(docked["faces"]) == ["0", "1"]   # the proposal's pose kept
    angle = (docked["fit"][0] - truth["2"][0] + 180) % 360 - 180
    centre = outlines["2"].mean(axis=0)                         # the error where the newcomer is, as evaluate measures it
    shift = np.hypot(*(_apply(docked["fit"], centre) - _apply(truth["2"], centre)))
    assert abs(angle) <= 3 and shift <= 3, (angle, shift)
    # the same from the function itself
    pose, faced = dock_newcomer(cluster, "0", "2", pieces)
    assert np.allclose(pose, docked["fit"]) and faced == docked["faces"]
    # kept: shown again without the outlines (the web page docks once); a member moved is a new docking
    cache = {}
    assert dock_next_joins(cluster, [plain], pieces, cache=cache) == [docked] and len(cache) == 1
    assert dock_next_joins(cluster, [plain], {}, cache=cache) == [docked]
    assert plain["fit"] is None                                # the entries given are not changed
    moved = Cluster(id="C:0", root="0", fragments=["0", "1"], poses={"0": truth["0"], "1": (35.0, 40.0, -4.0)},
                    joins=cluster.joins)
    assert dock_next_joins(moved, [plain], {}, cache=cache) == [plain]


def test_a_newcomer_that_meets_one_member_is_offered_no_fit():
    """Three strips side by side: C touches B only, so docking against the cluster {A, B} has nothing a single
    crack would not have: no fit is offered, the proposal's pose stays."""
    from types import SimpleNamespace

    from common.matching.reconstruction import Cluster

    def labels(x, y):
        return np.where(x < 20 + 1.5 * np.sin(y / 5.0), 0, np.where(x < 40 + 1.5 * np.sin(y / 4.0 + 2.0), 1, 2))

    truth = {"0": (0.0, 0.0, 0.0), "1": (20.0, 30.0, 10.0), "2": (70.0, 60.0, -20.0)}
    outlines = _framed(_broken_square(labels), truth)
    cluster = Cluster(id="C:0", root="0", fragments=["0", "1"], poses={"0": truth["0"], "1": truth["1"]},
                      joins=[Join("0", "1", *relative_pose(truth["0"], truth["1"]))])
    z = relative_pose(truth["1"], truth["2"])
    prop = SimpleNamespace(id=1, fragment_a="1", fragment_b="2", probability=0.9, mutual=0.9, status="pending",
                           angle_deg=z[0], tx_mm=z[1], ty_mm=z[2])
    got = next_joins(cluster, [prop], [cluster], pieces={k: (c, None) for k, c in outlines.items()})[0]
    assert got["fit"] is None and got["faces"] == []
    assert (got["pose"][0] - truth["2"][0] + 180) % 360 - 180 == pytest.approx(0, abs=1e-6)
    assert got["pose"][1:] == pytest.approx(truth["2"][1:], abs=1e-6)


def test_a_newcomer_proposed_to_two_members_is_docked_against_their_cluster_once(monkeypatch):
    """The reconstruction page docked a newcomer against a cluster once per proposal, so one proposed to two of its
    members was docked twice. The docking (the cluster's outline, the candidates and their geometry) is the same
    for both; the chooser's paint, scored across the proposal's own member's crack, is not. So it is docked once
    and each next join gets :func:`dock_newcomer`'s answer for its member: the same corner without paint, and
    another candidate where that member's paint says so."""
    from types import SimpleNamespace

    import common.matching.docking as docking
    import common.matching.paint as paint
    from common.matching.reconstruction import Cluster, dock_key, dock_newcomer, dock_next_joins

    truth = {"0": (0.0, 0.0, 0.0), "1": (35.0, 40.0, -5.0), "2": (-110.0, 50.0, 55.0)}
    outlines = _framed(_broken_square(_corner), truth)
    cluster = Cluster(id="C:0", root="0", fragments=["0", "1"], poses={"0": truth["0"], "1": truth["1"]},
                      joins=[Join("0", "1", *relative_pose(truth["0"], truth["1"]))])
    props = [SimpleNamespace(id=i, fragment_a=m, fragment_b="2", probability=0.9, mutual=0.9, status="pending",
                             angle_deg=z[0], tx_mm=z[1], ty_mm=z[2])
             for i, m in ((1, "0"), (2, "1")) for z in [relative_pose(truth[m], truth["2"])]]
    plain = next_joins(cluster, props, [cluster])
    assert sorted(d["member"] for d in plain) == ["0", "1"] and {d["newcomer"] for d in plain} == {"2"}
    calls = []
    real = docking.dock_outlines
    monkeypatch.setattr(docking, "dock_outlines", lambda *a, **k: calls.append(a) or real(*a, **k))

    def alone(member, pieces):   # dock_newcomer for one member, as the page did per proposal
        before = len(calls)
        pose, faced = dock_newcomer(cluster, member, "2", pieces)
        assert len(calls) == before + 1
        return tuple(float(v) for v in pose), faced

    pieces = {k: (c, None) for k, c in outlines.items()}
    cache = {}
    got = dock_next_joins(cluster, plain, pieces, cache=cache)
    assert len(calls) == 1 and len(cache) == 2                      # docked once, an answer per member
    for d in got:
        assert cache[dock_key(cluster, d["member"], "2")] == alone(d["member"], pieces)
        assert sorted(d["faces"]) == ["0", "1"] and d["fit"] == cache[dock_key(cluster, d["member"], "2")][0]
    assert got[0]["fit"] == got[1]["fit"]                           # no paint: the same corner for both
    # with paint, the member decides among the candidates: member 1's paint continues only at the last one
    monkeypatch.setattr(paint, "paint_continuity",
                        lambda field_m, field_n, poses: np.where(np.arange(len(poses)) == len(poses) - 1,
                                                                 1000.0 * (field_m == "paint of 1"), 0.0))
    painted = {k: (c, f"paint of {k}") for k, c in outlines.items()}
    calls.clear()
    cache = {}
    dock_next_joins(cluster, plain, painted, cache=cache)
    assert len(calls) == 1
    mine = {m: cache[dock_key(cluster, m, "2")] for m in ("0", "1")}
    assert mine == {m: alone(m, painted) for m in ("0", "1")} and mine["0"][0] != mine["1"][0]


def test_docking_a_newcomer_needs_every_outline():
    from common.matching.reconstruction import Cluster, dock_newcomer

    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    cluster = Cluster(id="C:A", root="A", fragments=["A", "B"], poses={"A": (0.0, 0.0, 0.0), "B": (0.0, 12.0, 0.0)},
                      joins=[Join("A", "B", 0.0, 12.0, 0.0)])
    with pytest.raises(ValueError, match=r"missing \['B'\]"):
        dock_newcomer(cluster, "A", "C", {"A": (sq, None), "C": (sq, None)})
    with pytest.raises(ValueError, match="newcomer 'B' in cluster: True"):
        dock_newcomer(cluster, "A", "B", {"A": (sq, None), "B": (sq, None)})


def station_with_a_cluster(root):
    """A station's storage under ``root``: six fragments of a small Pompeii-like wall with their front RGBN and
    feature tables (the first fragment without one), proposals of every pair at the true relative pose, and one
    pair of true neighbours confirmed (a cluster with a newcomer in its corner). Returns (wall, db path, (a, b))."""
    from common.features import extract_features, save_features
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from common.synth.wall import generate_wall

    wall = generate_wall(6, seed=2, dpi=30, preset="pompeii", colour_only=True, missing_fraction=0.0,
                         spurious_fraction=0.0)
    byid = {f.id: f for f in wall.fragments}
    store = Store(root)
    db = _proposal_store(root / "matches", wall, byid)
    for f in wall.fragments[1:]:                           # the first fragment has no feature table
        save_rgbn(store, f"fragments/{f.id}/rgbn/front-{f.id[-3:]}.h5", f.rgbn)
        ref = save_features(store, f"fragments/{f.id}/features/front-{f.id[-3:]}.h5",
                            extract_features(f.rgbn, face="front", fragment=f.id))
        db.add_fragment(f.id, "front", ref.to_dict())
    save_rgbn(store, f"fragments/{wall.fragments[0].id}/rgbn/front-000.h5", wall.fragments[0].rgbn)
    a, b, _ = next((a, b, n) for a, b, n in wall.adjacency if wall.fragments[0].id not in (a, b))
    db.record_verdict(a, b, "confirmed")
    db.close()
    return wall, root / "matches" / "proposals.sqlite", (a, b)


def test_cli_docks_the_next_joins_against_their_cluster_from_the_feature_tables(tmp_path):
    """``tessera reconstruct`` reads the members' and newcomers' feature tables and docks each next join's
    newcomer against its cluster, offering its fit where it fits a corner beside the proposal's pose;
    ``--no-dock`` offers none; a fragment whose feature table is missing gets none, nothing fails."""
    from services.cli import main

    wall, _, (a, b) = station_with_a_cluster(tmp_path / "store")

    def next_of(*extra):
        out = tmp_path / ("out" + "".join(extra))
        assert main(["reconstruct", "--store", str(tmp_path / "store"), "-o", str(out), "--json-only", *extra]) == 0
        (c,) = json.loads((out / "reconstruction.json").read_text())["clusters"]
        return c["next_joins"]

    docked, plain = next_of(), next_of("--no-dock")
    assert docked and {d["newcomer"] for d in docked} == {d["newcomer"] for d in plain}
    assert all(d["fit"] is None for d in plain)
    assert [d["pose"] for d in docked] == [d["pose"] for d in plain]   # the proposals' poses either way
    assert any(d["fit"] is not None for d in docked)   # this wall has a newcomer in the cluster's corner
    for d in docked:
        if d["fit"] is not None:
            assert set(d["faces"]) == {a, b}               # it fits between both members
        if d["newcomer"] == wall.fragments[0].id:
            assert d["fit"] is None                        # no outline to dock


def test_composite_files_declare_their_dpi(tmp_path):
    """The composite PNG and 16-bit TIFF carry the composite's sampling, so a measurement on them is in mm."""
    import tifffile
    from PIL import Image

    comp = {"albedo": np.full((12, 16, 3), 0.5, np.float32), "alpha": np.ones((12, 16), np.float32),
            "dpi": 93.75, "pixel_mm": 25.4 / 93.75}
    png, tif = write_composite(comp, tmp_path / "c.png", tmp_path / "c.tif")
    with Image.open(png) as im:
        assert im.info.get("dpi") == pytest.approx((93.75, 93.75), rel=1e-4)   # PNG: whole pixels per metre
    with tifffile.TiffFile(tif) as t:
        tags = t.pages[0].tags
        assert tags["ResolutionUnit"].value == 2                     # inch
        num, den = tags["XResolution"].value
        assert num / den == pytest.approx(93.75, abs=0.01)
