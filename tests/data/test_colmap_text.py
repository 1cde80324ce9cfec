"""The text-model reader used where pycolmap is absent, against pycolmap (the oracle) on every shared scene."""

import sys
from pathlib import Path

import numpy as np
import pytest

from kc_splatfacto.data.colmap import find_model_dir, read_colmap_model
from tests.conftest import shared_scene

SCENES = ("castle-P30", "entry-P10", "fern-12", "flower-12", "beer-12", "fountain-P11")


def read_without_pycolmap(model_dir: Path, monkeypatch):
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` raises ImportError
        return read_colmap_model(model_dir)


@pytest.mark.parametrize("scene", SCENES)
def test_text_reader_matches_pycolmap(scene, monkeypatch):
    pytest.importorskip("pycolmap")
    model_dir = find_model_dir(shared_scene(scene), None)
    if (model_dir / "cameras.bin").is_file():
        pytest.skip(f"{model_dir} is a binary model")
    oracle = read_colmap_model(model_dir)
    ours = read_without_pycolmap(model_dir, monkeypatch)
    assert ours.cameras.keys() == oracle.cameras.keys()
    for cid, camera in oracle.cameras.items():
        mine = ours.cameras[cid]
        assert (mine.model, mine.width, mine.height) == (camera.model, camera.width, camera.height)
        np.testing.assert_array_equal([mine.fx, mine.fy, mine.cx, mine.cy], [camera.fx, camera.fy, camera.cx, camera.cy])
        np.testing.assert_array_equal(mine.distortion, camera.distortion)
    assert [i.name for i in ours.images] == [i.name for i in oracle.images]
    assert [i.camera_id for i in ours.images] == [i.camera_id for i in oracle.images]
    for mine, image in zip(ours.images, oracle.images):
        np.testing.assert_allclose(mine.world_to_camera, image.world_to_camera, rtol=0, atol=1e-12)
    # the same points; their order is the file's here and pycolmap's hash map's there (an arbitrary seed order)
    def rows(model):
        table = np.concatenate([model.points_xyz, model.points_rgb.astype(np.float64)], axis=1)
        return table[np.lexsort(table.T[::-1])]

    assert len(ours.points_xyz) == len(oracle.points_xyz)
    np.testing.assert_array_equal(rows(ours), rows(oracle))
    assert len(ours.points_xyz) > 0


def write_model(folder: Path, images: str, points: str = "") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("# a comment\n1 PINHOLE 64 48 50 50 32 24\n")
    (folder / "images.txt").write_text(images)
    (folder / "points3D.txt").write_text(points)
    return folder


def test_empty_points_lines_and_comments(tmp_path, monkeypatch):
    """An image's 2D-points line may be empty; comments anywhere are skipped; poses are COLMAP's (w, x, y, z)."""
    images = ("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n"
              "1 1 0 0 0 0.5 0 2 1 a.png\n\n"
              "2 0.7071067811865476 0 0.7071067811865476 0 0 0 3 1 b c.png\n1.0 2.0 -1\n")
    points = "# POINT3D_ID X Y Z R G B ERROR TRACK[]\n7 0.1 0.2 5 255 0 10 0.5 1 0\n"
    model = read_without_pycolmap(write_model(tmp_path / "m", images, points), monkeypatch)
    assert [i.name for i in model.images] == ["a.png", "b c.png"]
    np.testing.assert_allclose(model.images[0].world_to_camera[:3, 3], [0.5, 0, 2])
    # a 90-degree turn about y: camera x is world -z (x' = R x with R = [[0,0,1],[0,1,0],[-1,0,0]])
    np.testing.assert_allclose(model.images[1].world_to_camera[:3, :3], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
                               atol=1e-15)
    np.testing.assert_array_equal(model.points_xyz, [[0.1, 0.2, 5]])
    np.testing.assert_array_equal(model.points_rgb, [[255, 0, 10]])


def test_binary_model_without_pycolmap_names_the_fix(tmp_path, monkeypatch):
    folder = tmp_path / "bin"
    folder.mkdir()
    for name in ("cameras", "images", "points3D"):
        (folder / f"{name}.bin").write_bytes(b"\0" * 8)
    with pytest.raises(ImportError, match="pip install pycolmap.*model_converter"):
        read_without_pycolmap(folder, monkeypatch)
