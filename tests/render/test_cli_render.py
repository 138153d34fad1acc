import cv2
import h5py
import numpy as np
import pytest
import tifffile

from common.rgbn.image import RGBNImage, write_rgbn
from common.rgbn.io import encode_normal_map, write_image
from services.cli import main
from tests.rgbn.analytic import sphere


@pytest.fixture
def files(tmp_path):
    n, mask = sphere(40, 1.8, 0.1)
    write_image(tmp_path / "n.png", encode_normal_map(n, mask, "directx"), bits=16)
    write_image(tmp_path / "a.png", np.full((40, 40, 3), 0.5))
    img = RGBNImage(albedo=np.full((40, 40, 3), 0.3), mask=mask, dpi=254.0, normals=n)
    with h5py.File(tmp_path / "img.h5", "w") as f:
        f.attrs["schema"] = "tessera.rgbn"
        write_rgbn(f, img)
    return tmp_path, n, mask


def test_render_an_rgbn_artifact_in_one_style_as_16_bit_tiff(files):
    tmp, n, mask = files
    assert main(["render", str(tmp / "img.h5"), "--style", "exaggerated", "-o", str(tmp / "x.tif"), "--bits", "16"]) == 0
    data = tifffile.imread(tmp / "x.tif")
    assert data.shape == (40, 40, 3) and data.dtype == np.uint16


def test_render_a_directx_normal_map_with_albedo_and_a_parameter(files):
    tmp, n, mask = files
    out = tmp / "lit.png"
    rc = main(["render", "--normals", str(tmp / "n.png"), "--albedo", str(tmp / "a.png"), "--convention", "directx",
               "--style", "lambertian", "-p", "light=[90,30]", "-p", "ambient=0", "-p", "colour=false", "-o", str(out)])
    assert rc == 0
    grey = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)[..., 1].astype(float) / 255
    # light from the top (azimuth 90): the upper half of the sphere is brighter, as it would be
    # only if the DirectX green axis was flipped on reading
    assert grey[8:16, 16:24].mean() > grey[24:32, 16:24].mean() + 0.2


def test_render_with_a_recipe_file(files, tmp_path):
    tmp, n, mask = files
    recipe = tmp / "r.toml"
    recipe.write_text('name = "mine"\nbits = 16\n[[layer]]\nstyle = "mean_curvature"\n')
    assert main(["render", str(tmp / "img.h5"), "--recipe", str(recipe), "-o", str(tmp / "r.png")]) == 0
    assert cv2.imread(str(tmp / "r.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16


def test_cli_errors_are_plain_messages_with_status_2(files, capsys):
    tmp, n, mask = files
    assert main(["render", str(tmp / "img.h5"), "--style", "nope", "-o", str(tmp / "x.png")]) == 2
    assert "unknown style 'nope'" in capsys.readouterr().err
    assert main(["render", str(tmp / "img.h5"), "--style", "toon"]) == 2
    assert "-o" in capsys.readouterr().err
    assert main(["render", "--list-styles"]) == 0
    out = capsys.readouterr().out
    assert "exaggerated" in out
    # each style's description is whole, not its docstring's first line cut mid-sentence
    assert "highlights show slope;" in out


def test_render_normals_reads_through_the_door_checks(files, capsys):
    """A truncated normal map, or 8-bit values in a 16-bit file, is refused naming the file; nothing written."""
    tmp, n, mask = files
    data = (tmp / "n.png").read_bytes()
    (tmp / "cut.png").write_bytes(data[: len(data) // 2])
    out = tmp / "cut-out.png"
    assert main(["render", "--normals", str(tmp / "cut.png"), "--style", "lambertian", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cut.png" in err and "truncated" in err
    assert not out.exists()
    eight = np.round(encode_normal_map(n, mask, "opengl") * 255).astype(np.uint16)     # 8-bit values, 16-bit file
    cv2.imwrite(str(tmp / "n8in16.png"), eight[..., 2::-1] if eight.shape[2] == 3 else eight[..., [2, 1, 0, 3]])
    assert main(["render", "--normals", str(tmp / "n8in16.png"), "--style", "lambertian", "-o", str(out)]) == 2
    assert "8-bit values" in capsys.readouterr().err
    assert not out.exists()
