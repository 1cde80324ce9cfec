"""Image decoding edge cases (issue 26): float images scaled by their real range (or refused), decompression bombs
refused before decoding, alpha kept through the downscale cache whatever the source's suffix."""

import os
import struct
import zlib

import cv2
import numpy as np
import pytest

from kc_splatfacto.data.base import READ_ONLY_DATA_ENV, DataParserError
from kc_splatfacto.data.images import derived_root, downscaled_paths, image_size, read_image


def test_float_tiff_in_0_255_reads_as_its_8_bit_values(tmp_path):
    rng = np.random.default_rng(0)
    eight_bit = rng.integers(0, 256, (20, 30, 3)).astype(np.uint8)
    path = tmp_path / "f.tif"
    cv2.imwrite(str(path), eight_bit.astype(np.float32))
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).dtype == np.float32
    np.testing.assert_array_equal(read_image(path), eight_bit[..., ::-1])  # BGR file -> RGB


def test_float_tiff_in_0_1_is_quantized(tmp_path):
    values = np.linspace(0.0, 1.0, 20 * 30 * 3, dtype=np.float32).reshape(20, 30, 3)
    path = tmp_path / "u.tif"
    cv2.imwrite(str(path), values)
    expected = np.round(values[..., ::-1].astype(np.float64) * 255.0).astype(np.uint8)
    np.testing.assert_array_equal(read_image(path), expected)


@pytest.mark.parametrize("scale, offset", [(1.0, -0.5), (300.0, 0.0), (-1.0, 0.0)])
def test_float_tiff_outside_both_ranges_is_refused_with_its_range(tmp_path, scale, offset):
    values = (np.linspace(0.0, 1.0, 600, dtype=np.float32).reshape(10, 20, 3) * scale + offset).astype(np.float32)
    path = tmp_path / "bad.tif"
    cv2.imwrite(str(path), values)
    with pytest.raises(DataParserError, match=f"{path} is a float image with values in"):
        read_image(path)


def bomb_png(width, height):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 16)) + chunk(b"IEND", b"")


def test_decompression_bomb_is_refused_from_its_header(tmp_path):
    path = tmp_path / "bomb.png"
    path.write_bytes(bomb_png(40000, 40000))  # 1.6 G pixels claimed in 100 bytes
    for read in (image_size, read_image):
        with pytest.raises(DataParserError, match=f"{path} is refused as a decompression bomb"):
            read(path)


@pytest.mark.parametrize("name", ["rgba.jpg", "rgba.webp", "rgba.png"])
def test_alpha_survives_the_downscale_cache(tmp_path, name):
    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, (24, 32, 4)).astype(np.uint8)
    rgba[:, :16, 3] = 0  # a transparent half
    images = tmp_path / "images"
    images.mkdir()
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    (images / name).write_bytes(png.tobytes())  # PNG bytes whatever the suffix says
    (cached,) = downscaled_paths([images / name], images, 2)
    got = read_image(cached)
    expected = cv2.resize(rgba, (16, 12), interpolation=cv2.INTER_AREA)
    assert got.shape == (12, 16, 4)
    np.testing.assert_array_equal(got, expected)  # lossless, alpha included
    assert cached.suffix == ".png"
    assert downscaled_paths([images / name], images, 2) == [cached]  # found again, not rewritten


# ------------------------------------------------------------------------------------------------ read-only in intent
# Issue 58 item 6: with ../shared writable (a contributor's clone), commands the suite starts (ns-train, the GPU
# campaign's dry run) wrote images_4 / images_8 into the shared scenes. A folder named by $KC_SPLATFACTO_READ_ONLY_DATA
# is read-only in intent: derived images of its scenes go to the cache, in this process and in every one it starts.


def test_a_scene_under_read_only_data_derives_into_the_cache_though_writable(tmp_path, monkeypatch):
    from tests.hostile_scenes import colmap_scene, tree_digest

    data = tmp_path / "shared-copy"
    scene = colmap_scene(data / "scene")
    images = scene / "images"
    paths = sorted(images.iterdir())
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv(READ_ONLY_DATA_ENV, raising=False)
    assert derived_root(images, None) == scene  # writable and not named: the scene holds its derived images
    monkeypatch.setenv(READ_ONLY_DATA_ENV, f"{tmp_path / 'elsewhere'}{os.pathsep}{data}")
    before = tree_digest(data)
    assert (tmp_path / "cache") in derived_root(images, None).parents
    written = downscaled_paths(paths, images, 2, None)
    assert tree_digest(data) == before  # nothing written into the (writable) scene
    assert all((tmp_path / "cache") in p.parents and p.is_file() for p in written)


def test_commands_the_suite_starts_treat_a_writable_shared_folder_as_read_only(tmp_path):
    """A kc-train started as the suite starts commands (its environment inherited) on a writable copy of a scene under
    the folder the suite names: the downscaled images go to the cache, the copy is unchanged."""
    import subprocess
    import sys

    from tests.conftest import SHARED_DATA
    from tests.hostile_scenes import colmap_scene, tree_digest

    assert str(SHARED_DATA.resolve()) in os.environ[READ_ONLY_DATA_ENV].split(os.pathsep)  # set by tests/conftest.py
    data = tmp_path / "shared-copy"
    scene = colmap_scene(data / "scene")
    before = tree_digest(data)
    env = {**os.environ, "KC_SPLATFACTO_CACHE": str(tmp_path / "cache"), "OMP_WAIT_POLICY": "PASSIVE",
           READ_ONLY_DATA_ENV: os.pathsep.join([os.environ[READ_ONLY_DATA_ENV], str(data)])}
    done = subprocess.run(
        [sys.executable, "-m", "kc_splatfacto.cli.train", "splatfacto", "--data", str(scene), "--output-dir",
         str(tmp_path / "out"), "--max-num-iterations", "1", "--steps-per-eval-all-images", "0",
         "--logging.progress-bar", "False", "--final-lpips-nets", "--machine.device", "cpu",
         "--pipeline.model.num-downscales", "0", "colmap",
         "--downscale-factor", "2"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert tree_digest(data) == before
    assert list((tmp_path / "cache").rglob("images_2"))
