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


def test_judgement_sheet_shows_each_column_at_1_to_1_in_the_windows_it_names():
    """The judgement sheet's crops are the drawings' own pixels (1:1), the most-relief window
    holds the relief, the darkest window the dark paint, and each column carries its label."""
    import cv2

    from common.render.gallery import JUDGEMENT_COLUMNS, JUDGEMENT_CROP, judgement_sheet, judgement_windows
    from common.rgbn.image import RGBNImage
    from tests.rgbn.analytic import gaussian_bump

    h, w = 400, 600
    n = np.zeros((h, w, 3), np.float32)
    n[..., 2] = 1.0
    n[40:200, 330:490] = gaussian_bump(160, 0.05, 0.5, 0.5)        # relief, upper right
    albedo = np.full((h, w, 3), 0.6, np.float32)
    albedo[250:390, 20:250] = 0.05                               # dark paint, away from the relief
    image = RGBNImage(albedo=albedo, mask=np.ones((h, w), bool), dpi=300.0, normals=n)
    wins = judgement_windows(image)
    relief, dark = wins["most relief"], wins["darkest colour"]
    assert 330 - JUDGEMENT_CROP[1] < relief[1].start < 490 and 40 - JUDGEMENT_CROP[0] < relief[0].start < 200
    assert dark[0].start >= 250 - 30 and dark[1].stop <= 250 + 30
    drawn = {recipe: np.random.default_rng(j).uniform(0, 1, (h, w, 3)).astype(np.float32)
             for j, (_, recipe) in enumerate(JUDGEMENT_COLUMNS)}
    sheet, figures = judgement_sheet("test", image, drawn)
    assert sheet.dtype == np.uint8 and set(figures) == {label for label, _ in JUDGEMENT_COLUMNS}
    for _, recipe in JUDGEMENT_COLUMNS:
        crop = np.round(drawn[recipe][dark] * 255).astype(np.uint8)
        hits = cv2.matchTemplate(sheet, crop, cv2.TM_SQDIFF)   # float sums: locate, then compare exactly
        y, x = np.unravel_index(int(np.argmin(hits)), hits.shape)
        assert np.array_equal(sheet[y:y + crop.shape[0], x:x + crop.shape[1]], crop), \
            f"{recipe}: the 1:1 crop is not on the sheet pixel for pixel"
    # labels: dark text above each column, nothing but white where there is none
    top = sheet[30:70]
    assert (top < 128).any() and (sheet[:, -4:] == 255).all()


def test_the_page_describes_every_style_in_whole_sentences():
    """docs/gallery.md (drawn by this module) gives each style its docstring's first paragraph:
    its first line alone stopped mid-sentence ("... highlights show")."""
    from pathlib import Path

    from common.render.recipes import STYLES

    page = (Path(__file__).resolve().parents[2] / "docs" / "gallery.md").read_text()
    for name, style in STYLES.items():
        assert style.summary.endswith((".", ")")), name
        if f"### {name}\n" in page:
            assert f"### {name}\n\n{style.summary}\n" in page, name


def test_the_page_states_the_parameters_as_the_code_does():
    from pathlib import Path

    from common.render.gallery import _recipe_reference

    page = (Path(__file__).resolve().parents[2] / "docs" / "gallery.md").read_text()
    assert _recipe_reference() in page


def test_the_page_starts_with_the_modules_head():
    """docs/gallery.md is written by ``python -m common.render.gallery`` as HEAD, a blank line, then the
    rest: a correction made to the page alone would be undone by the next regeneration."""
    from pathlib import Path

    from common.render.gallery import HEAD

    page = (Path(__file__).resolve().parents[2] / "docs" / "gallery.md").read_text()
    assert page.startswith(HEAD.rstrip() + "\n\n")
