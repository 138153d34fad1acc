"""Which fresco a piece comes from: signatures, the same-fresco ratio, and its place in the ranking."""

import numpy as np
import pytest

from common.matching import fresco as F


def _plaster_piece(rng, lab_ground, n=400, paint=None, paint_share=0.0, mottle=1.0):
    """CIELAB samples of a piece: plaster around ``lab_ground`` (mottled), some painted samples."""
    lab = np.asarray(lab_ground, float) + rng.normal(0, [mottle, 0.3 * mottle, 0.3 * mottle], (n, 3))
    k = int(round(paint_share * n))
    if k:
        lab[:k] = np.asarray(paint, float) + rng.normal(0, 1.0, (k, 3))
    return lab


def test_lab_signature_reads_plaster_spread_paint_and_palette():
    rng = np.random.default_rng(0)
    red, black_blue = (45.0, 30.0, 20.0), (35.0, 2.0, -20.0)
    lab = _plaster_piece(rng, (70.0, 1.0, 4.0), n=1000, mottle=2.0)
    lab[:150] = np.asarray(red) + rng.normal(0, 1.0, (150, 3))
    lab[150:250] = np.asarray(black_blue) + rng.normal(0, 1.0, (100, 3))
    s = F.lab_signature(lab)
    assert s.plaster_lab == pytest.approx([70.0, 1.0, 4.0], abs=0.3)
    assert s.plaster_spread_l == pytest.approx(2.0, rel=0.15)          # 1.4826 MAD of a normal = its sigma
    assert s.painted_share == pytest.approx(0.25, abs=0.01)
    assert len(s.palette_lab) == 2
    assert s.palette_lab[0] == pytest.approx(red, abs=1.0)             # commonest first
    assert s.palette_lab[1] == pytest.approx(black_blue, abs=1.0)
    assert s.palette_share == pytest.approx([0.6, 0.4], abs=0.02)
    assert s.chroma_hist.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="at least 3"):
        F.lab_signature(np.zeros((2, 3)))


def test_chroma_distance_is_zero_for_one_distribution_and_grows_with_the_tint():
    rng = np.random.default_rng(1)
    a = F.lab_signature(_plaster_piece(rng, (70, 1, 4), n=4000))
    b = F.lab_signature(_plaster_piece(rng, (70, 1, 4), n=4000))
    c = F.lab_signature(_plaster_piece(rng, (70, 1, 6), n=4000))
    d = F.lab_signature(_plaster_piece(rng, (70, 1, 9), n=4000))
    far = F.lab_signature(_plaster_piece(rng, (50, 30, 30), n=4000))
    assert F.chroma_distance(a, a) == pytest.approx(0.0, abs=1e-6)
    assert F.chroma_distance(a, b) == pytest.approx(F.chroma_distance(b, a))
    assert F.chroma_distance(a, b) < 0.05 < F.chroma_distance(a, c) < F.chroma_distance(a, d)
    assert F.chroma_distance(a, far) == 10.0                            # disjoint: capped


def test_ratio_fitted_on_walls_that_differ_by_construction_tells_them_apart():
    """Four 'frescoes' with their own plaster tint (pieces mottled and faded a little): the ratio fitted
    on them is higher for pairs of one fresco; on a fresh draw of such frescoes (not fitted) too."""
    def collection(seed):
        rng = np.random.default_rng(seed)
        sigs, groups = [], []
        for w in range(4):
            ground = (68.0 + rng.normal(0, 2), 1.0 + rng.normal(0, 1.0), 3.0 + rng.normal(0, 2.0))
            for _ in range(8):
                piece = np.asarray(ground) + rng.normal(0, [1.0, 0.2, 0.3])   # piece-to-piece fading
                sigs.append(F.lab_signature(_plaster_piece(rng, piece)))
                groups.append(w)
        return sigs, groups

    sigs, groups = collection(2)
    params = F.fit_fresco_llr(sigs, groups)
    assert params["coef"][0] < 0                       # farther histograms: less likely one fresco
    assert params["n_same"] == 4 * 28 and params["n_different"] == 6 * 64
    sigs2, groups2 = collection(3)
    g = np.asarray(groups2)
    i, j = np.triu_indices(len(g), 1)
    r = np.array([F.fresco_llr(sigs2[a], sigs2[b], params) for a, b in zip(i, j)])
    same = g[i] == g[j]
    auc = (r[same][:, None] > r[~same][None, :]).mean()
    assert auc > 0.85, auc
    assert np.median(r[same]) > 0 > np.median(r[~same])  # a log-likelihood ratio: its sign means something
    assert np.all(np.abs(r) <= params["clip"])
    with pytest.raises(ValueError, match="pairs of one fresco"):
        F.fit_fresco_llr(sigs[:4], [0, 1, 2, 3])


def test_with_fresco_adds_the_ratio_to_the_logit():
    p = np.array([0.2, 0.5, 0.9])
    out = F.with_fresco(p, np.array([np.log(4.0), 0.0, np.nan]))
    assert out[0] == pytest.approx(0.5)                 # odds 1/4 × 4
    assert out[1] == pytest.approx(0.5) and out[2] == pytest.approx(0.9)
    assert F.with_fresco(0.5, np.log(3.0), weight=2.0) == pytest.approx(0.9)


def test_factory_walls_of_one_house_share_their_plaster():
    """generate_wall(house_plaster=True): two walls of one palette are closer in plaster tint than two of
    different palettes; the option changes only colours (the same pieces, the same outlines)."""
    from common.synth.realistic import plaster_palette, wall_ground
    from common.synth.wall import generate_wall

    pal = plaster_palette(9)
    assert np.any([np.allclose(pal["house_ground"], g) for g in pal["grounds"]])
    assert wall_ground(pal, 1) == pytest.approx(wall_ground(pal, 1))
    assert not np.allclose(wall_ground(pal, 1), wall_ground(pal, 2))
    with pytest.raises(ValueError, match="house_ground"):
        wall_ground({"grounds": pal["grounds"]}, 1)
    a = generate_wall(6, seed=31, dpi=20, preset="pompeii", colour_only=True, palette_seed=9)
    b = generate_wall(6, seed=31, dpi=20, preset="pompeii", colour_only=True, palette_seed=9, house_plaster=True)
    assert a.id != b.id
    assert all(np.array_equal(x.rgbn.mask, y.rgbn.mask) for x, y in zip(a.fragments, b.fragments))


def test_ranking_lifts_a_candidate_of_the_querys_fresco(monkeypatch):
    """MatchIndex._rank_by_fresco: with equal earlier evidence, a candidate whose boundary colours are
    the query's plaster comes before one of another plaster, by exactly the fitted ratio."""
    from common.features.boundary import boundary_channel_names
    from common.matching.index import Candidate, MatchIndex
    from common.matching.pairs import FragmentCues, _descs

    names = boundary_channel_names()
    rng = np.random.default_rng(4)
    nf = len(_descs()[0])

    def profile(rgb_lin):
        p = np.zeros((200, len(names)), np.float32)
        for d in ("0.8", "1.6"):
            for k, c in enumerate("rgb"):
                p[:, names.index(f"sqrt_{c}@{d}")] = np.sqrt(rgb_lin[k] * (1 + rng.normal(0, 0.01, 200)))
        return p

    index = MatchIndex()
    for fid, rgb in (("q", (0.40, 0.37, 0.34)), ("same", (0.40, 0.37, 0.34)), ("other", (0.40, 0.36, 0.30))):
        values = np.full(nf, np.nan)
        cues = FragmentCues(fid, values, np.zeros((0, 1)), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)))
        index._raw_profiles[fid] = profile(rgb)
        index.cues[fid] = cues
    cands = [Candidate("q", o, 0.3, -1, -1, np.zeros((0, 2), int), np.zeros((0, 1))) for o in ("other", "same")]
    monkeypatch.setattr(F, "FRESCO_WEIGHT", 0.0)
    assert [c.other for c in index._rank_by_fresco("q", list(cands))] == ["other", "same"]
    monkeypatch.setattr(F, "FRESCO_WEIGHT", 1.0)
    ranked = index._rank_by_fresco("q", list(cands))
    assert [c.other for c in ranked] == ["same", "other"]
    sq, ss = index._fresco_signature("q"), index._fresco_signature("same")
    assert ranked[0].fresco_llr == pytest.approx(F.fresco_llr(sq, ss))
    assert ranked[0].probability == pytest.approx(float(F.with_fresco(0.3, ranked[0].fresco_llr)))
