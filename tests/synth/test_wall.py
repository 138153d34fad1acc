import numpy as np
import pytest
from scipy import ndimage

from common.synth.wall import _Look, _plan, _render_piece, generate_wall


@pytest.fixture(scope="module")
def wall():
    return generate_wall(16, seed=11, dpi=60)


def test_same_seed_gives_identical_data():
    a = generate_wall(5, seed=4, dpi=40)
    b = generate_wall(5, seed=4, dpi=40)
    assert a.id == b.id and a.adjacency == b.adjacency
    for fa, fb in zip(a.fragments, b.fragments):
        assert fa.id == fb.id and fa.pose == fb.pose
        assert np.array_equal(fa.rgbn.albedo, fb.rgbn.albedo)
        assert np.array_equal(fa.rgbn.normals, fb.rgbn.normals)
        assert np.array_equal(fa.surface.back.height_mm, fb.surface.back.height_mm)
    c = generate_wall(5, seed=5, dpi=40)
    assert c.id != a.id and not np.array_equal(c.fragments[0].rgbn.mask.shape, a.fragments[0].rgbn.mask.shape) \
        or not np.array_equal(c.fragments[0].rgbn.albedo, a.fragments[0].rgbn.albedo)


def test_parallel_rendering_gives_the_same_wall():
    a = generate_wall(4, seed=8, dpi=40)
    b = generate_wall(4, seed=8, dpi=40, workers=2)
    assert a.adjacency == b.adjacency
    for fa, fb in zip(a.fragments, b.fragments):
        assert fa.id == fb.id and np.array_equal(fa.rgbn.albedo, fb.rgbn.albedo)


def test_counts_missing_and_spurious_fragments(wall):
    assert len(wall.fragments) == 16 and len({f.id for f in wall.fragments}) == 16
    spurious = [f for f in wall.fragments if f.spurious]
    assert len(spurious) == 1 and spurious[0].pose is None
    pieces = len(wall.fragments) - len(spurious) + wall.n_missing
    assert 0.1 <= wall.n_missing / pieces <= 0.3
    in_pairs = {i for a, b, _ in wall.adjacency for i in (a, b)}
    assert spurious[0].id not in in_pairs
    assert all(a < b for a, b, _ in wall.adjacency)


def test_fragments_show_the_wall_painting_at_their_pose(wall):
    ref = wall.preview["albedo"]
    g = wall.preview["grid_mm"]
    checked = 0
    for f in wall.fragments:
        if f.spurious or f.notes:  # faded/discoloured ones no longer match their neighbours
            continue
        pm = f.rgbn.pixel_mm
        inner = ndimage.binary_erosion(f.rgbn.mask, iterations=int(2.0 / pm))
        rr, cc = np.nonzero(inner)
        w = f.to_wall(np.column_stack([cc, rr]) * pm) / g
        expect = np.stack([ndimage.map_coordinates(ref[..., k], [w[:, 1], w[:, 0]], order=1) for k in range(3)], 1)
        assert np.median(np.abs(f.rgbn.albedo[rr, cc] - expect)) < 0.03, f.id
        checked += 1
    assert checked >= 5


def test_correspondences_meet_on_the_wall(wall):
    assert len(wall.adjacency) >= 10
    gaps = []
    for a, b, length in wall.adjacency:
        pa, pb = wall.correspondences[(a, b)]
        assert len(pa) == len(pb) >= 0.3 * length  # about one per mm of shared crack
        wa, wb = wall.fragment(a).to_wall(pa), wall.fragment(b).to_wall(pb)
        gap = np.hypot(*(wa - wb).T)
        # eroded and chipped edges no longer touch, but corresponding points stay close
        assert np.median(gap) < 4.0
        gaps.append(gap)
    assert 0.3 < np.median(np.concatenate(gaps)) < 2.5


def test_adjacency_is_the_pieces_that_touch_on_the_wall(wall):
    lab = wall.preview["labels"]
    ids = wall.preview["label_ids"]
    touching = {}
    for a, b in ((lab[:, 1:], lab[:, :-1]), (lab[1:], lab[:-1])):
        sel = (a != b) & (a >= 0) & (b >= 0)
        for u, v in zip(a[sel], b[sel]):
            if ids[u] and ids[v]:
                key = tuple(sorted((ids[u], ids[v])))
                touching[key] = touching.get(key, 0) + 1
    truth = {(a, b) for a, b, _ in wall.adjacency}
    # every ground-truth pair touches on the 1 mm map, every long shared crack is a pair
    assert truth <= set(touching)
    assert {k for k, n in touching.items() if n >= 8} <= truth


def test_normals_are_rotated_with_the_fragment():
    rng = np.random.default_rng(0)
    plan = _plan(6, rng, rng, rng, mode="recursive", style="aegean", image=None, median_size_mm=30, sigma=0.5,
                 jag_mm=1.5)
    c = plan.fracture.coarse_labels
    lab = int(np.argmax(np.bincount(c[c >= 0])))
    sl = ndimage.find_objects((c == lab).astype(int))[0]
    bbox = ((sl[0].start, sl[0].stop), (sl[1].start, sl[1].stop))
    f1, _ = _render_piece(plan, lab, bbox, 80.0, np.random.default_rng(1), look=_Look(0.0, True), spurious=False)
    f2, _ = _render_piece(plan, lab, bbox, 80.0, np.random.default_rng(2), look=_Look(0.0, True), spurious=False)
    assert abs(f1.pose[0] - f2.pose[0]) > 20

    def wall_normals(f, p):
        # fragment-frame (x right, y up) normal -> wall frame (x right, y up)
        pm = f.rgbn.pixel_mm
        rc = np.round(p / pm).astype(int)
        n = f.rgbn.normals[rc[:, 1], rc[:, 0]]
        a = np.deg2rad(f.pose[0])
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        xy_down = np.column_stack([n[:, 0], -n[:, 1]]) @ R.T
        return np.column_stack([xy_down[:, 0], -xy_down[:, 1], n[:, 2]])

    pm = f1.rgbn.pixel_mm
    inner = ndimage.binary_erosion(f1.rgbn.mask, iterations=int(3 / pm))
    rr, cc = np.nonzero(inner)
    p1 = np.column_stack([cc, rr]) * pm
    p2 = f2.from_wall(f1.to_wall(p1))
    ok = np.all((p2 >= 0) & (p2 / pm < np.array(f2.rgbn.mask.shape[::-1]) - 1), axis=1)
    n1, n2 = wall_normals(f1, p1[ok]), wall_normals(f2, p2[ok])
    ang = np.degrees(np.arccos(np.clip(np.sum(n1 * n2, axis=1), -1, 1)))
    tilt = np.degrees(np.arccos(np.clip(n1[:, 2], -1, 1)))
    assert np.median(tilt) > 1.0  # there is relief to compare
    assert np.median(ang) < 0.35 * np.median(tilt)


def test_voronoi_mode_and_sizes():
    w = generate_wall(10, seed=2, dpi=40, mode="voronoi", median_size_mm=35)
    sizes = np.sqrt([f.area_mm2 for f in w.fragments])
    assert len(w.fragments) == 10 and len(w.adjacency) >= 5
    assert np.all(sizes > 8) and np.all(sizes < 200)
    assert 15 < np.median(sizes) < 60


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="n_fragments"):
        generate_wall(0, seed=1)
    with pytest.raises(ValueError, match="mode"):
        generate_wall(3, seed=1, mode="shatter")
    with pytest.raises(ValueError, match="missing_fraction"):
        generate_wall(3, seed=1, missing_fraction=1.5)


def test_a_user_picture_becomes_the_painted_layer():
    img = np.zeros((60, 90, 3), np.uint8)
    img[:, :45] = (200, 30, 30)   # left half red, right half blue (sRGB)
    img[:, 45:] = (30, 30, 200)
    w = generate_wall(6, seed=1, dpi=30, image=img, image_width_mm=180, spurious_fraction=0)
    assert w.width_mm == pytest.approx(180, abs=1)
    for f in w.fragments:
        if f.notes:
            continue
        rr, cc = np.nonzero(ndimage.binary_erosion(f.rgbn.mask, iterations=3))
        x_wall = f.to_wall(np.column_stack([cc, rr]) * f.rgbn.pixel_mm)[:, 0]
        a = f.rgbn.albedo[rr, cc]
        left, right = x_wall < 80, x_wall > 100
        assert np.all(a[left, 0] > a[left, 2]) and np.all(a[right, 2] > a[right, 0])


def test_colour_continues_across_true_joins_but_not_between_strangers(wall):
    """The premise of matching (§5.2): edge colours of true neighbours agree far better than chance."""
    def edge_colour(f, pts):
        # mean albedo of a 2 mm disc 1.5 mm inside the contour, at each given contour point
        pm = f.rgbn.pixel_mm
        inner = ndimage.binary_erosion(f.rgbn.mask, iterations=max(1, int(1.5 / pm)))
        rr, cc = np.nonzero(inner)
        xy = np.column_stack([cc, rr]) * pm
        out = []
        for p in pts:
            d = np.hypot(*(xy - p).T)
            sel = d < d.min() + 2.0
            out.append(f.rgbn.albedo[rr[sel], cc[sel]].mean(axis=0))
        return np.array(out)

    clean = {f.id for f in wall.fragments if not f.notes and not f.spurious}
    true_d, rng = [], np.random.default_rng(0)
    for a, b, _ in wall.adjacency:
        if a in clean and b in clean:
            pa, pb = wall.correspondences[(a, b)]
            ca, cb = edge_colour(wall.fragment(a), pa[::3]), edge_colour(wall.fragment(b), pb[::3])
            true_d.append(np.abs(ca - cb).sum(axis=1))
    ids = sorted(clean)
    rand_d = []
    for _ in range(30):
        a, b = rng.choice(ids, 2, replace=False)
        if wall.is_neighbour(a, b):
            continue
        fa, fb = wall.fragment(a), wall.fragment(b)
        pa = fa.contour_mm[rng.integers(0, len(fa.contour_mm), 5)]
        pb = fb.contour_mm[rng.integers(0, len(fb.contour_mm), 5)]
        rand_d.append(np.abs(edge_colour(fa, pa) - edge_colour(fb, pb)).sum(axis=1))
    assert len(true_d) >= 5
    assert np.median(np.concatenate(true_d)) < 0.5 * np.median(np.concatenate(rand_d))


def test_shared_length_of_a_straight_crack_is_its_chord():
    # no jaggedness and no erosion: two pieces split by one straight crack across the wall
    w = generate_wall(2, seed=3, dpi=50, missing_fraction=0, spurious_fraction=0, jag_mm=0.0, erosion_mm=0.0)
    (a, b, length), = w.adjacency
    lab, g = w.preview["labels"], w.preview["grid_mm"]
    h_edge = (lab[:, 1:] != lab[:, :-1]) & (lab[:, 1:] >= 0) & (lab[:, :-1] >= 0)
    v_edge = (lab[1:] != lab[:-1]) & (lab[1:] >= 0) & (lab[:-1] >= 0)
    (r1, c1), (r2, c2) = np.nonzero(h_edge), np.nonzero(v_edge)
    pts = np.vstack([np.column_stack([c1 + 0.5, r1]), np.column_stack([c2, r2 + 0.5])]) * g
    d = np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2][0]  # the crack's direction
    s = (pts - pts.mean(0)) @ d
    chord = s.max() - s.min() + g
    assert length == pytest.approx(chord, rel=0.05)  # the chord is read off a 1 mm map


def test_the_simulated_flatbed_sees_the_rgbn_normals_on_the_surface():
    """FragmentSurface (for the flatbed) and RGBNImage (direct) describe the same face."""
    from common.acquisition.flatbed_sim import SimulatedFlatbed
    w = generate_wall(3, seed=1, dpi=80, missing_fraction=0, spurious_fraction=0)
    f = w.fragments[0]
    H, W = f.rgbn.shape
    pm = f.rgbn.pixel_mm
    sim = SimulatedFlatbed(seed=0)
    sim.place(f.surface, angle_deg=0.0, centre_mm=(100.0, 150.0))
    left, top = 100 - W * pm / 2, 150 - H * pm / 2
    truth = sim.truth((left, top, left + W * pm, top + H * pm), dpi=80)
    assert truth.shape == (H, W)
    inner = ndimage.binary_erosion(truth.mask & f.rgbn.mask, iterations=3)
    assert inner.sum() > 0.5 * f.rgbn.mask.sum()
    cos = np.sum(truth.normals[inner] * f.rgbn.normals[inner], axis=1)
    assert np.median(np.degrees(np.arccos(np.clip(cos, -1, 1)))) < 0.5
    assert np.median(np.abs(truth.albedo[inner] - f.rgbn.albedo[inner])) < 0.01
