import numpy as np
import pytest

from common.synth.breakage import fracture_recursive, fracture_voronoi
from common.synth.noise import affine_grid


@pytest.mark.parametrize("make", [fracture_recursive, fracture_voronoi])
def test_exact_piece_count_and_log_normal_sizes(make):
    f = make(330, 220, np.random.default_rng(0), median_size_mm=30, sigma=0.6, n_pieces=60)
    lab = f.coarse_labels
    areas = np.bincount(lab[lab >= 0].ravel(), minlength=f.n_pieces)
    assert f.n_pieces == 60 and np.all(areas > 0)
    logd = np.log(np.sqrt(areas * f.grid_mm ** 2))
    # the wall's area sets the scale: median size near the square root of the mean area
    assert np.exp(np.median(logd)) == pytest.approx(np.sqrt(areas.sum() / 60), rel=0.35)
    assert 0.15 < logd.std() < 0.8  # a spread of sizes, not a regular grid


@pytest.mark.parametrize("make", [fracture_recursive, fracture_voronoi])
def test_grid_labels_equal_the_exact_partition(make):
    f = make(200, 150, np.random.default_rng(1), median_size_mm=30, n_pieces=20)
    pm = 0.2
    a = np.deg2rad(70)
    G = np.array([[pm * np.cos(a), -pm * np.sin(a), 120.0], [pm * np.sin(a), pm * np.cos(a), 10.0]])
    x, y = affine_grid(G, (300, 350))
    exact = f.labels(x, y)
    # the grid path interpolates the coarse octaves of the crack displacement: a few pixels
    # exactly on a crack may fall on the other side, nothing more
    assert np.mean(f.labels_grid(G, (300, 350)) != exact) < 1e-3
    piece = exact[150, 175]
    near = f.labels_grid(G, (300, 350), near=piece)
    assert np.mean((near == piece) != (exact == piece)) < 1e-3


def test_cracks_are_jagged_and_shared():
    smooth = fracture_recursive(100, 100, np.random.default_rng(2), median_size_mm=60, n_pieces=2, jag_mm=0.0)
    jagged = fracture_recursive(100, 100, np.random.default_rng(2), median_size_mm=60, n_pieces=2, jag_mm=1.5)

    def boundary_length(f):
        x, y = np.meshgrid(np.arange(0, 100, 0.1, dtype=np.float32), np.arange(0, 100, 0.1, dtype=np.float32))
        lab = f.labels(x, y)
        edge = (lab[:, 1:] != lab[:, :-1]) & (lab[:, 1:] >= 0) & (lab[:, :-1] >= 0)
        edge2 = (lab[1:, :] != lab[:-1, :]) & (lab[1:, :] >= 0) & (lab[:-1, :] >= 0)
        return edge.sum() + edge2.sum()
    # the same crack made jagged is markedly longer in pixel edges
    assert boundary_length(jagged) > 1.3 * boundary_length(smooth)


def test_successive_cracks_are_roughly_perpendicular():
    f = fracture_recursive(400, 400, np.random.default_rng(3), median_size_mm=25, n_pieces=150, angle_jitter_deg=10)
    angles = []
    for node in range(len(f.left)):
        if f.leaf_label[node] >= 0:
            continue
        for child in (f.left[node], f.right[node]):
            if f.leaf_label[child] < 0:
                cosang = abs(f.nx[node] * f.nx[child] + f.ny[node] * f.ny[child])
                angles.append(np.degrees(np.arccos(min(cosang, 1.0))))
    # Shin et al. 2012: a piece breaks across its longest axis -> mostly near 90 degrees
    assert np.median(angles) > 60


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="median_size_mm"):
        fracture_recursive(100, 100, np.random.default_rng(0), median_size_mm=0)
    with pytest.raises(ValueError, match="n_pieces"):
        fracture_voronoi(100, 100, np.random.default_rng(0), n_pieces=0)
