"""``spars3r`` as nerfstudio's dataparser: the 12 training views and the test list (for nerfstudio's "val" and "test"
splits alike), cameras that nerfstudio's own ``get_viewmat`` turns back into the project's viewmats, the seed points
where nerfstudio's Splatfacto looks for them, and the project's errors for a broken scene."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")

from kc_splatfacto.data.base import DataParserError  # noqa: E402
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.dataparser import Spars3rNerfstudioDataParserConfig  # noqa: E402
from tests.conftest import shared_scene  # noqa: E402


def test_the_splits_are_the_lists_and_the_cameras_nerfstudios_convention():
    from nerfstudio.models.splatfacto import get_viewmat

    scene = shared_scene("castle-P30")
    parser = Spars3rNerfstudioDataParserConfig(data=scene, downscale_factor=4).setup()
    ours = Spars3rDataParserConfig(data=scene, downscale_factor=4).setup()
    for split, listing in (("train", "train_list.txt"), ("val", "test_list.txt"), ("test", "test_list.txt")):
        outputs = parser.get_dataparser_outputs(split)
        expected = ours.get_dataparser_outputs(split)
        names = (scene / listing).read_text().split()
        assert [p.name for p in outputs.image_filenames] == [p.name for p in expected.image_filenames]
        assert len(outputs.image_filenames) == len(names) == 12
        cameras = outputs.cameras
        viewmats = get_viewmat._torchdynamo_orig_callable(cameras.camera_to_worlds)  # nerfstudio's own conversion
        assert torch.allclose(viewmats, expected.cameras.viewmats, atol=1e-5)
        assert torch.equal(cameras.get_intrinsics_matrices(), expected.cameras.Ks.float())
        assert cameras.width[:, 0].tolist() == expected.cameras.widths.tolist()
    train = parser.get_dataparser_outputs("train")
    assert train.metadata["points3D_xyz"].shape[1] == 3 and train.metadata["points3D_rgb"].dtype == torch.uint8
    assert torch.equal(train.metadata["points3D_xyz"], ours.get_dataparser_outputs("train").points3d_xyz.float())


def test_a_broken_scene_is_the_projects_error(tmp_path):
    (tmp_path / "images").mkdir()
    (tmp_path / "train_list.txt").write_text("a.png\n")
    (tmp_path / "test_list.txt").write_text("")
    with pytest.raises(DataParserError, match="test list .* is empty"):
        Spars3rNerfstudioDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
