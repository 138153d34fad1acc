"""Tests of common/acquisition/handheld.py and the ``tessera ps`` command."""

import contextlib
import json

import cv2
import numpy as np
import pytest
import tifffile

from common.acquisition.handheld import (cast_shadows, handheld_rgbn, object_mask, read_images, read_mask,
                                         simulate_flash_capture, sphere_lights, surface_normals)
from common.acquisition.lightfile import LightSet, write_lp
from common.acquisition.spheres import sphere_normals
from common.acquisition.surface import FragmentSurface
from common.rgbn.image import load_rgbn, read_rgbn
from common.store import Store
from services.cli import main as tessera


def _lights(n, seed=0, min_elevation=30):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(min_elevation, 80, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _fragment(size=64, dpi=254.0):
    """A tilted, gently waved plaster face on a dark table (mask = the face)."""
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    px = 25.4 / dpi
    mask = (np.abs(cols - size / 2) < size * 0.35) & (np.abs(rows - size / 2) < size * 0.3)
    height = (0.2 * cols + 0.1 * np.sin(rows / 5)) * px + 1.0
    albedo = np.dstack([np.full((size, size), v) for v in (0.8, 0.6, 0.4)]).astype(np.float32)
    return FragmentSurface(albedo, np.where(mask, height, 0.0), mask, dpi)


def test_images_of_every_format_read_as_linear_rgb(tmp_path):
    red = np.zeros((6, 5, 3), np.uint8)
    red[..., 0] = 200  # RGB red
    red[0, :, 0] = [0, 50, 100, 150, 200]  # some contrast: a uniform frame is refused as blank
    cv2.imwrite(str(tmp_path / "a.png"), red[..., ::-1])
    cv2.imwrite(str(tmp_path / "b.png"), (red[..., ::-1].astype(np.uint16) * 257))
    tifffile.imwrite(tmp_path / "c.tif", red.astype(np.uint16) * 257, photometric="rgb")
    cv2.imwrite(str(tmp_path / "d.jpg"), red[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    cv2.imwrite(str(tmp_path / "e.png"), red[..., 0])  # grey
    # one stack holds one bit depth and one channel layout: each format is read on its own
    images = np.concatenate([read_images([tmp_path / n])[0] for n in ("a.png", "b.png", "c.tif", "d.jpg", "e.png")])
    assert images.shape == (5, 6, 5, 3) and images.dtype == np.float32
    for i in range(3):
        np.testing.assert_allclose(images[i, 2, 2], [200 / 255, 0, 0], atol=1e-6)
    np.testing.assert_allclose(images[3, 2, 2], [200 / 255, 0, 0], atol=0.05)  # JPEG loss (8x8 block with the contrast row)
    np.testing.assert_allclose(images[4, 2, 2], [200 / 255] * 3, atol=1e-6)
    _, saturated = read_images([tmp_path / "a.png", tmp_path / "a.png"])
    assert not saturated.any()
    lin, _ = read_images([tmp_path / "a.png"], srgb=True)
    assert abs(lin[0, 2, 2, 0] - ((200 / 255 + 0.055) / 1.055) ** 2.4) < 1e-5


def test_clipped_pixels_are_flagged_saturated(tmp_path):
    img = np.full((4, 4, 3), 100, np.uint8)
    img[1, 1, 2] = 255
    cv2.imwrite(str(tmp_path / "s.png"), img)
    _, saturated = read_images([tmp_path / "s.png"])
    assert saturated[0].sum() == 1 and saturated[0, 1, 1]


def test_image_of_another_size_is_named(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.arange(16, dtype=np.uint8).reshape(4, 4) * 9)
    cv2.imwrite(str(tmp_path / "b.png"), np.arange(20, dtype=np.uint8).reshape(5, 4) * 9)
    with pytest.raises(ValueError, match="b.png"):
        read_images([tmp_path / "a.png", tmp_path / "b.png"])
    with pytest.raises(ValueError, match="missing.png: does not exist"):
        read_images([tmp_path / "missing.png"])


def test_surface_normals_of_a_tilted_plane():
    dpi = 254.0
    rows, cols = np.mgrid[0:8, 0:8].astype(float)
    # rising to the right by 0.5 mm per mm and towards the top of the image by 0.25 mm per mm
    height = (0.5 * cols - 0.25 * rows) * 25.4 / dpi
    n = surface_normals(FragmentSurface(np.zeros((8, 8, 3)), height, np.ones((8, 8), bool), dpi))
    expect = np.array([-0.5, -0.25, 1.0]) / np.linalg.norm([-0.5, -0.25, 1.0])
    np.testing.assert_allclose(n[4, 4], expect, atol=1e-6)


def test_cast_shadow_length_follows_the_light_elevation():
    height = np.zeros((20, 40), np.float32)
    height[:, 10:12] = 1.0  # a 1 mm wall, pixels of 0.1 mm
    light = np.array([-np.cos(np.radians(30)), 0.0, np.sin(np.radians(30))])  # from the left, 30° up
    shadow = cast_shadows(height, 0.1, light)
    # shadow right of the wall: 1 mm / tan(30°) = 1.73 mm = 17 pixels
    assert shadow[10, 12:29].all() and not shadow[10, 30:].any() and not shadow[10, :10].any()


def test_object_mask_finds_the_lit_fragment():
    surf = _fragment()
    images = simulate_flash_capture(surf, _lights(8))
    found = object_mask(images)
    assert (found == surf.mask).mean() > 0.98


def test_handheld_capture_becomes_an_rgbn_image_with_the_fragment_normals():
    surf = _fragment()
    lights = _lights(20, seed=1)
    e = np.linspace(0.6, 1.2, 20)
    images = simulate_flash_capture(surf, lights, intensities=e, specular=0.4, shininess=200)
    rgbn = handheld_rgbn(images, LightSet(lights, intensities=e), mask=surf.mask,
                         saturated=images.max(-1) >= 0.995, dpi=surf.dpi)
    truth = surface_normals(surf)
    inner = cv2.erode(surf.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err = np.degrees(np.arccos(np.clip((rgbn.normals * truth).sum(-1), -1, 1)))[inner]
    assert err.mean() < 0.5
    np.testing.assert_allclose(rgbn.albedo[inner].mean(0), [0.8, 0.6, 0.4], atol=0.02)
    assert rgbn.discontinuity.shape == surf.mask.shape + (2,)
    assert rgbn.attrs["capture"] == "handheld-flash" and rgbn.dpi == surf.dpi


def test_unknown_method_is_refused():
    with pytest.raises(ValueError, match="method"):
        handheld_rgbn(np.ones((3, 4, 4, 3), np.float32), np.eye(3) + [0, 0, 1], method="magic")


def test_sphere_lights_from_rendered_spheres():
    shape, circle = (80, 80), (40.0, 40.0, 30.0)
    lights = _lights(6, seed=2)
    e = np.linspace(0.8, 1.2, 6)
    normals, inside = sphere_normals(shape, circle)
    refl = 2 * normals[..., 2:3] * normals - [0, 0, 1]
    chrome = np.stack([np.where(inside, np.exp(-(np.degrees(np.arccos(np.clip(refl @ l, -1, 1))) / 6) ** 2), 0)
                       for l in lights]).astype(np.float32)
    diffuse = np.stack([0.5 * ei * np.clip(normals @ l, 0, None) for l, ei in zip(lights, e)]).astype(np.float32)
    got = sphere_lights(chrome, circle, diffuse_images=diffuse, diffuse_circle=circle)
    assert np.degrees(np.arccos(np.clip((got.directions * lights).sum(1), -1, 1))).max() < 0.5
    np.testing.assert_allclose(got.intensities[:, 0], e / e.mean(), rtol=0.01)


def _write_capture(tmp_path, n=12):
    surf = _fragment()
    lights = _lights(n, seed=3)
    images = simulate_flash_capture(surf, lights)
    names = []
    for i, img in enumerate(images):
        name = f"shot_{i:02d}.png"
        cv2.imwrite(str(tmp_path / name), (np.round(img * 65535).astype(np.uint16))[..., ::-1])
        names.append(name)
    # the .lp lists the shots in another order: matched by name
    write_lp(tmp_path / "capture.lp", names[::-1], lights[::-1])
    cv2.imwrite(str(tmp_path / "mask.png"), surf.mask.astype(np.uint8) * 255)
    return surf, [str(tmp_path / nm) for nm in names]


def test_ps_command_writes_a_content_keyed_artifact_and_the_event(tmp_path, capsys):
    surf, shots = _write_capture(tmp_path)
    store = tmp_path / "store"
    args = ["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
            "--store", str(store), "--fragment", "F0007", "--face", "back", "--dpi", "254",
            "-o", str(tmp_path / "out.h5"), "--pictures", str(tmp_path / "pics")]
    assert tessera(args) == 0
    out = capsys.readouterr().out
    event = json.loads(out[out.index("{"):out.rindex("}") + 1])
    assert event["type"] == "rgbn.ready" and event["fragment"] == "F0007" and event["face"] == "back"
    path = event["artifact"]["path"]
    assert path.startswith("fragments/F0007/rgbn/back-") and path.endswith(".h5")
    rgbn = load_rgbn(Store(store), event["artifact"])
    truth = surface_normals(surf)
    inner = cv2.erode(surf.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.degrees(np.arccos(np.clip((rgbn.normals * truth).sum(-1), -1, 1)))[inner].mean() < 0.5
    assert rgbn.dpi == 254 and rgbn.discontinuity is not None
    import h5py
    with h5py.File(tmp_path / "out.h5", "r") as f:
        assert f.attrs["schema"] == "tessera.rgbn"
        np.testing.assert_array_equal(read_rgbn(f).mask, rgbn.mask)
    assert {p.name for p in (tmp_path / "pics").iterdir()} == {"normals.png", "albedo.png", "confidence.png",
                                                               "discontinuity.png"}
    # a second run over the same inputs finds the same artifact (content-keyed, idempotent)
    assert tessera(args) == 0
    again = capsys.readouterr().out
    assert json.loads(again[again.index("{"):again.rindex("}") + 1])["artifact"] == event["artifact"]


def test_ps_rerun_with_other_settings_writes_a_new_artifact(tmp_path, capsys):
    # docs/handheld.md: re-running is harmless -- so a run with another --dpi or --srgb must not
    # find the first run's artifact in place and announce it as its own
    _, shots = _write_capture(tmp_path)
    base = ["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
            "--store", str(tmp_path / "store"), "--fragment", "F1", "--method", "least_squares",
            "--no-discontinuities"]

    def artifact(*extra):
        assert tessera(base + list(extra)) == 0
        out = capsys.readouterr().out
        return json.loads(out[out.index("{"):out.rindex("}") + 1])["artifact"]

    first = artifact()
    assert artifact() == first                       # same inputs and settings: the same artifact
    # the same images for the same face at another dpi would be a second, rescaled copy: refused as by every
    # import, naming both dpi values, unless --replace
    assert tessera(base + ["--dpi", "300"]) == 2
    assert ("the same file is already imported for fragment F1 (front) at 96 dpi; this import gives 300 dpi: give "
            "--replace") in capsys.readouterr().err
    at_300 = artifact("--dpi", "300", "--replace")
    assert at_300["path"] != first["path"]
    assert load_rgbn(Store(tmp_path / "store"), at_300).dpi == 300
    assert artifact("--srgb")["path"] not in (first["path"], at_300["path"])


def test_ps_command_refuses_ambiguous_lights(tmp_path, capsys):
    _, shots = _write_capture(tmp_path, n=4)
    code = tessera(["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--chrome", "auto", "-o",
                    str(tmp_path / "x.h5")])
    assert code == 2 and "exactly one of --lights" in capsys.readouterr().err


def test_ps_command_calibrates_from_the_seitz_spheres(shared_data, tmp_path, capsys):
    root = shared_data / "psm-seitz"
    imgs = lambda obj: [str(root / obj / f"{obj}.{i:02d}.png") for i in range(12)]  # noqa: E731
    lp = tmp_path / "owl.lp"
    assert tessera(["ps", *imgs("owl"), "--mask", str(root / "owl" / "owl.mask.png"),
                    "--chrome", str(root / "chrome" / "chrome.mask.png"), "--chrome-images", *imgs("chrome"),
                    "--diffuse", str(root / "gray" / "gray.mask.png"), "--diffuse-images", *imgs("gray"),
                    "--write-lp", str(lp), "-o", str(tmp_path / "owl.h5")]) == 0
    from common.acquisition.lightfile import read_lights
    got = read_lights(lp)
    ref = read_lights(root / "lights.txt")
    assert got.filenames[0] == "owl.00.png"
    assert np.degrees(np.arccos(np.clip((got.directions * ref.directions).sum(1), -1, 1))).mean() < 4.0
    import h5py
    with h5py.File(tmp_path / "owl.h5", "r") as f:
        owl = read_rgbn(f)
    mask = read_mask(root / "owl" / "owl.mask.png")
    assert owl.normals[mask, 2].mean() > 0.6 and owl.confidence[mask].mean() > 0.7


def test_ps_command_calibrates_from_a_mirror_sphere_in_the_frame(tmp_path, capsys):
    size, dpi = 64, 254.0
    surf = _fragment(size, dpi)
    # widen the scene: the fragment on the left, a mirror sphere on the table to its right
    wide = FragmentSurface(np.pad(surf.albedo, ((0, 0), (0, 56), (0, 0))), np.pad(surf.height_mm, ((0, 0), (0, 56))),
                           np.pad(surf.mask, ((0, 0), (0, 56))), dpi)
    lights = _lights(10, seed=6)
    images = simulate_flash_capture(wide, lights)
    circle = (92.0, 32.0, 20.0)
    normals, inside = sphere_normals(images.shape[1:3], circle)
    refl = 2 * normals[..., 2:3] * normals - [0, 0, 1]
    shots = []
    for i, (img, l) in enumerate(zip(images, lights)):
        chrome = np.exp(-(np.degrees(np.arccos(np.clip(refl @ l, -1, 1))) / 8) ** 2) + 0.03
        img[inside] = chrome[inside, None]
        shots.append(str(tmp_path / f"f{i}.png"))
        cv2.imwrite(shots[-1], np.round(img * 65535).astype(np.uint16)[..., ::-1])
    assert tessera(["ps", *shots, "--spheres", "92,32,20", "--write-lp", str(tmp_path / "l.lp"),
                    "-o", str(tmp_path / "o.h5")]) == 0
    from common.acquisition.lightfile import read_lights
    got = read_lights(tmp_path / "l.lp").directions
    assert np.degrees(np.arccos(np.clip((got * lights).sum(1), -1, 1))).max() < 1.0
    import h5py
    with h5py.File(tmp_path / "o.h5", "r") as f:
        rgbn = read_rgbn(f)
    assert not rgbn.mask[inside].any()  # the sphere is not part of the object
    assert (rgbn.mask == wide.mask).mean() > 0.97
    truth = surface_normals(wide)
    inner = cv2.erode(wide.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.degrees(np.arccos(np.clip((rgbn.normals * truth).sum(-1), -1, 1)))[inner].mean() < 1.0


@contextlib.contextmanager
def _station(tmp_path):
    """A broker on loopback and the station config naming it and a storage root: ``(config path, config)``."""
    import socket
    import threading

    from common.bus.broker import Broker
    from common.config import load_config

    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    cfg_path = tmp_path / "station.toml"
    cfg_path.write_text(f'[storage]\nroot = "{tmp_path / "storage"}"\n'
                        f'[broker]\nhost = "127.0.0.1"\nbind = "127.0.0.1"\nport = {ports[0]}\nfeed_port = {ports[1]}\n'
                        f'journal_dir = "{tmp_path / "journal"}"\n[client]\ntimeout_s = 1.0\nretries = 3\n')
    config = load_config(cfg_path)
    stop = threading.Event()
    broker = threading.Thread(target=Broker(config).run, args=(stop,), daemon=True)
    broker.start()
    try:
        yield cfg_path, config
    finally:
        stop.set()
        broker.join(10)


def _events(config, min_count=1):
    """The events the broker journaled (waits up to 10 s for ``min_count``)."""
    import time

    from common.bus.client import BrokerClient
    from common.messages import unpack

    with BrokerClient.from_config(config) as bus:
        deadline = time.monotonic() + 10
        events = []
        while time.monotonic() < deadline and len(events) < min_count:
            events = [unpack(e) for _, e in bus.since(0)["events"]]
            time.sleep(0.05)
    return events


def test_ps_command_submits_rgbn_ready_to_the_broker(tmp_path, capsys):
    with _station(tmp_path) as (cfg_path, config):
        _, shots = _write_capture(tmp_path, n=6)
        code = tessera(["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
                        "--fragment", "F0009", "--submit", "--config", str(cfg_path), "--no-discontinuities"])
        assert code == 0, capsys.readouterr().err
        assert "submitted rgbn.ready" in capsys.readouterr().out
        ready = [e for e in _events(config) if e["type"] == "rgbn.ready"]
        assert len(ready) == 1 and ready[0]["fragment"] == "F0009"
        # the artifact is in the station's storage root, where the workers will look
        rgbn = load_rgbn(Store(tmp_path / "storage"), ready[0]["artifact"])
        assert rgbn.normals is not None and rgbn.discontinuity is None


def test_ps_submit_of_the_same_capture_under_a_second_id_is_refused_naming_the_first(tmp_path, capsys):
    """``tessera ps --submit`` wrote a face without the check every import makes: the same capture submitted
    again under another fragment id became a second fragment, proposed as a join to the first. It is refused,
    naming the first, before anything is written or announced; ``--allow-duplicates`` submits it anyway. The
    light file and mask are the rig's (not compared); the images are checked."""
    with _station(tmp_path) as (cfg_path, config):
        _, shots = _write_capture(tmp_path, n=6)
        base = [*shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
                "--submit", "--config", str(cfg_path), "--no-discontinuities"]
        assert tessera(["ps", *base, "--fragment", "F-FIRST"]) == 0, capsys.readouterr().err
        capsys.readouterr()
        assert tessera(["ps", *base, "--fragment", "F-AGAIN"]) == 2
        err = capsys.readouterr().err
        assert ("shot_00.png: the same file (sha256 " in err
                and "is already imported as fragment F-FIRST (front, 96 dpi: fragments/F-FIRST/rgbn/front-" in err
                and "not imported again as F-AGAIN (front): give --allow-duplicates" in err), err
        assert not (tmp_path / "storage" / "fragments" / "F-AGAIN").exists()
        assert [e["fragment"] for e in _events(config) if e["type"] == "rgbn.ready"] == ["F-FIRST"]
        # the same capture for its own fragment again is no duplicate (a re-run is harmless)
        assert tessera(["ps", *base, "--fragment", "F-FIRST"]) == 0
        assert tessera(["ps", *base, "--fragment", "F-AGAIN", "--allow-duplicates"]) == 0
        ready = [e["fragment"] for e in _events(config, min_count=3) if e["type"] == "rgbn.ready"]
        assert ready == ["F-FIRST", "F-FIRST", "F-AGAIN"]


def test_ps_command_keeps_the_artifact_when_the_broker_is_away(tmp_path, capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nobody listens here
    cfg_path = tmp_path / "station.toml"
    cfg_path.write_text(f'[storage]\nroot = "{tmp_path / "storage"}"\n[broker]\nhost = "127.0.0.1"\nport = {port}\n'
                        f'journal_dir = "{tmp_path / "journal"}"\n[client]\ntimeout_s = 0.2\nretries = 1\n')
    _, shots = _write_capture(tmp_path, n=5)
    code = tessera(["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
                    "--fragment", "F0010", "--submit", "--config", str(cfg_path), "--no-discontinuities"])
    assert code == 1 and "not submitted" in capsys.readouterr().err
    assert len(list((tmp_path / "storage" / "fragments" / "F0010" / "rgbn").glob("front-*.h5"))) == 1


def test_ps_command_finds_both_spheres_by_itself(tmp_path):
    size, dpi = 64, 254.0
    surf = _fragment(size, dpi)
    pad = ((0, 36), (0, 136))
    wide = FragmentSurface(np.pad(surf.albedo, pad + ((0, 0),)), np.pad(surf.height_mm, pad),
                           np.pad(surf.mask, pad), dpi)
    lights = _lights(12, seed=7)
    e = np.linspace(0.7, 1.3, 12)
    images = simulate_flash_capture(wide, lights, intensities=e)
    mirror, diffuse = (100.0, 50.0, 26.0), (165.0, 48.0, 27.0)
    nm, im = sphere_normals(images.shape[1:3], mirror)
    nd, idf = sphere_normals(images.shape[1:3], diffuse)
    refl = 2 * nm[..., 2:3] * nm - [0, 0, 1]
    shots = []
    for i, (img, l) in enumerate(zip(images, lights)):
        img[im] = (np.exp(-(np.degrees(np.arccos(np.clip(refl @ l, -1, 1))) / 6) ** 2) + 0.02)[im, None]
        img[idf] = (0.6 * e[i] * np.clip(nd @ l, 0, None))[idf, None]
        shots.append(str(tmp_path / f"f{i}.tif"))
        tifffile.imwrite(shots[-1], np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), photometric="rgb")
    assert tessera(["ps", *shots, "--spheres", "auto", "auto", "--write-lp", str(tmp_path / "l.lp"),
                    "-o", str(tmp_path / "o.h5")]) == 0
    from common.acquisition.lightfile import read_lights
    got = read_lights(tmp_path / "l.lp").directions
    assert np.degrees(np.arccos(np.clip((got * lights).sum(1), -1, 1))).max() < 1.5
    import h5py
    with h5py.File(tmp_path / "o.h5", "r") as f:
        rgbn = read_rgbn(f)
    assert not (rgbn.mask & (im | idf)).any()  # neither sphere is part of the object
    truth = surface_normals(wide)
    inner = cv2.erode(wide.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.degrees(np.arccos(np.clip((rgbn.normals * truth).sum(-1), -1, 1)))[inner].mean() < 1.0
    # the diffuse sphere measured the flashes (mean 1): the albedo comes out as the surface's
    np.testing.assert_allclose(rgbn.albedo[inner].mean(0), [0.8, 0.6, 0.4], atol=0.02)


# --- door checks of read_images (issue 16) ---------------------------------------------------

def _shot(size=(40, 48), seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(0.1, 0.9, size + (3,)) * 255).astype(np.uint8)


def test_truncated_png_and_jpeg_are_refused_naming_the_file(tmp_path):
    for ext in ("png", "jpg"):
        good, cut = tmp_path / f"good.{ext}", tmp_path / f"cut.{ext}"
        cv2.imwrite(str(good), _shot())
        data = good.read_bytes()
        cut.write_bytes(data[:len(data) * 2 // 3])
        assert cv2.imread(str(cut)) is not None or ext == "png"  # OpenCV alone would accept the JPEG
        with pytest.raises(ValueError, match=f"cut.{ext}.*truncated"):
            read_images([good, cut])


def test_stacks_mixing_bit_depth_or_channels_are_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), _shot())
    cv2.imwrite(str(tmp_path / "b.png"), _shot(seed=1).astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "c.png"), _shot(seed=2)[..., 0])
    with pytest.raises(ValueError, match="b.png is 16-bit, the first image is 8-bit"):
        read_images([tmp_path / "a.png", tmp_path / "b.png"])
    with pytest.raises(ValueError, match="c.png is grey, the first image is RGB"):
        read_images([tmp_path / "a.png", tmp_path / "c.png"])


def test_eight_bit_values_in_a_sixteen_bit_file_are_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), _shot().astype(np.uint16))  # 0..255 in a 16-bit container
    with pytest.raises(ValueError, match="a.png.*16-bit.*8-bit"):
        read_images([tmp_path / "a.png"])


def test_black_blank_and_overexposed_images_are_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "ok.png"), _shot())
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((40, 48, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((40, 48, 3), 120, np.uint8))
    burnt = _shot()
    burnt[:30] = 255
    cv2.imwrite(str(tmp_path / "burnt.png"), burnt)
    for name, why in (("black", "black"), ("grey", "blank"), ("burnt", "saturated on 75%")):
        with pytest.raises(ValueError, match=f"{name}.png.*{why}"):
            read_images([tmp_path / "ok.png", tmp_path / f"{name}.png"])


# --- automatic mask from what varies with the light (issue 16) --------------------------------

def test_object_mask_covers_a_frame_filling_textured_object():
    size = 96
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    rng = np.random.default_rng(4)
    blobs = cv2.GaussianBlur(rng.uniform(0, 1, (size, size)).astype(np.float32), (0, 0), 6)
    blobs = (blobs - blobs.min()) / (blobs.max() - blobs.min())
    grey = 0.04 + 0.8 * (blobs > 0.5)  # dark and light paint (1:20), half the frame each, touching the border
    albedo = np.dstack([grey, grey * 0.9, grey * 0.8]).astype(np.float32)
    height = 0.3 * np.sin(cols / 9) * np.cos(rows / 13)
    surf = FragmentSurface(albedo, height, np.ones((size, size), bool), 254.0)
    images = simulate_flash_capture(surf, _lights(24, seed=2), noise=0.002)
    info = {}
    found = object_mask(images, info=info)
    assert not info["background"] and found.mean() > 0.99


def test_object_mask_keeps_shadows_and_dark_paint_of_a_thick_piece():
    size = 96
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    piece = (np.abs(cols - 48) < 28) & (np.abs(rows - 48) < 22)
    grey = np.where(piece, np.where(cols < 36, 0.1, 0.7), 0.01)  # dark paint on the piece's left, black velvet
    albedo = np.dstack([grey] * 3).astype(np.float32)
    height = np.where(piece, 2.0, 0.0)  # 2 mm thick at 254 dpi: shadows up to 40 px long on the velvet
    surf = FragmentSurface(albedo, height, np.ones((size, size), bool), 254.0)
    images = simulate_flash_capture(surf, _lights(24, seed=5, min_elevation=25), noise=0.001)
    found = object_mask(images)
    assert (found & piece).sum() / (found | piece).sum() > 0.95


def test_object_mask_too_small_asks_for_a_mask_file():
    surf = _fragment()
    images = simulate_flash_capture(surf, _lights(12))
    with pytest.raises(ValueError, match="covers only 42.8% of the frame.*--mask"):
        object_mask(images, min_share=0.5)


@pytest.mark.data
def test_object_mask_on_real_captures(shared_data):
    lp = shared_data / "realrti-dev"
    for item in ("item1", "item5", "item8"):
        images, _ = read_images(sorted((lp / item).glob("*.jpg")), srgb=True)
        assert object_mask(images).mean() > 0.99, item  # frame-filling: the object is the frame
    for obj in ("cat", "owl"):
        root = shared_data / "psm-seitz" / obj
        images, _ = read_images(sorted(root.glob(f"{obj}.[0-9]*.png")))
        truth = read_mask(root / f"{obj}.mask.png")
        found = object_mask(images)
        assert (found & truth).sum() / (found | truth).sum() > 0.97, obj
    root = shared_data / "diligent-ball"
    images, _ = read_images([root / n.strip() for n in (root / "filenames.txt").read_text().split()])
    truth = read_mask(root / "mask.png")
    found = object_mask(images)
    assert (found & truth).sum() / (found | truth).sum() > 0.98


# --- near lights of a dome capture (issue 16) --------------------------------------------------

def _dome_plane(h=60, w=80, radius=240.0, n=30):
    from common.acquisition.photometric import point_light_field

    rng = np.random.default_rng(7)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(25, 80, n))
    dirs = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d, f = point_light_field(radius * dirs, (h, w))
    grey = (0.5 * np.clip(d[..., 2], 0, None) * f).T.reshape(n, h, w)
    return dirs, (grey[..., None] * np.array([1.0, 0.9, 0.8])).astype(np.float32)


def test_dome_radius_is_found_and_the_plane_comes_out_flat():
    from common.acquisition.handheld import estimate_dome_radius, normal_tilt_gradient, rerender_residual

    dirs, images = _dome_plane(radius=240.0)  # 3 frame widths
    radius, table = estimate_dome_radius(images, dirs)
    assert radius == pytest.approx(240.0)
    assert table[0][0] is None and table[0][1] > 0.01  # distant lights cannot explain the images
    far = handheld_rgbn(images, dirs, mask=np.ones(images.shape[1:3], bool), discontinuities=False)
    near = handheld_rgbn(images, dirs, mask=np.ones(images.shape[1:3], bool), discontinuities=False,
                         dome_radius=radius)
    gx_far, gy_far = normal_tilt_gradient(far)
    gx, gy = normal_tilt_gradient(near)
    assert gx_far > 10 and gy_far > 10  # the plane seems to bulge: normals swing outwards across the frame
    assert abs(gx) < 0.05 and abs(gy) < 0.05
    assert rerender_residual(images, dirs, near, dome_radius=radius).max() < 1e-3
    assert rerender_residual(images, dirs, far).mean() > 0.01


def test_distant_lights_are_kept_when_no_dome_fits_better():
    from common.acquisition.handheld import estimate_dome_radius

    surf = _fragment()
    images = simulate_flash_capture(surf, _lights(12), shadows=False)
    radius, _ = estimate_dome_radius(images, _lights(12), mask=surf.mask)
    assert radius is None


def test_a_truncated_mask_file_is_refused_naming_it(tmp_path):
    # OpenCV alone decodes it with the missing rows grey, which read as object
    import cv2

    m = np.zeros((64, 64), np.uint8)
    m[16:48, 16:48] = 255
    path = tmp_path / "obj.mask.png"
    cv2.imwrite(str(path), m)
    assert read_mask(path).sum() == 32 * 32
    path.write_bytes(path.read_bytes()[:-30])
    with pytest.raises(ValueError, match="obj.mask.png.*truncated"):
        read_mask(path)
