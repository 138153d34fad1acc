import numpy as np

from common.render.gallery import ball
from common.render.shading import lambertian


def test_diligent_ball_ground_truth_follows_the_tessera_convention(shared_data):
    # row 0 at the top and y up: lit from above (azimuth 90), the upper half of the ball is brighter;
    # lit from the right (azimuth 0), the right half is
    image = ball(shared_data)
    rows, cols = np.nonzero(image.mask)
    cy, cx = rows.mean(), cols.mean()
    top = lambertian(image.normals, (90.0, 30.0))
    right = lambertian(image.normals, (0.0, 30.0))
    upper, lower = image.mask & (np.arange(image.shape[0])[:, None] < cy), image.mask & (np.arange(image.shape[0])[:, None] > cy)
    left_half = image.mask & (np.arange(image.shape[1])[None, :] < cx)
    right_half = image.mask & (np.arange(image.shape[1])[None, :] > cx)
    assert top[upper].mean() > top[lower].mean() + 0.3
    assert right[right_half].mean() > right[left_half].mean() + 0.3
    assert np.allclose(np.linalg.norm(image.normals[image.mask], axis=1), 1, atol=1e-3)
