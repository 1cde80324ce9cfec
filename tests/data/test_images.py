"""Image decoding edge cases (issue 26): float images scaled by their real range (or refused), decompression bombs
refused before decoding, alpha kept through the downscale cache whatever the source's suffix."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.images import downscaled_paths, image_size, read_image


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
