"""``spars3r`` for nerfstudio: the project's SPARS3R parser (12 training views, the scene's test list) behind
nerfstudio's ``DataParser``, so ``ns-train kc-splatfacto --data SCENE spars3r`` trains on the paper's sparse split.

The settings are :class:`~kc_splatfacto.data.spars3r.Spars3rDataParserConfig`'s (inherited, same names and defaults
as ``kc-train ... spars3r``); the parse, its checks and its errors are the project's; this module only converts its
outputs into nerfstudio's: OpenCV world-to-camera matrices into nerfstudio's OpenGL camera-to-world, the seed points
into ``metadata["points3D_xyz"]`` / ``["points3D_rgb"]`` (what nerfstudio's Splatfacto starts from).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser
from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig as NerfstudioDataParserConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs as NerfstudioOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from kc_splatfacto.data.outputs import DataparserOutputs
from kc_splatfacto.data.spars3r import Spars3rDataParser, Spars3rDataParserConfig
from kc_splatfacto.nerfstudio_plugin.cpu import OPENGL_TO_OPENCV


@dataclass
class Spars3rNerfstudioDataParserConfig(NerfstudioDataParserConfig, Spars3rDataParserConfig):
    """A SPARS3R-style sparse-view scene: images/, train_list.txt, test_list.txt, COLMAP sparse/0 (kc-splatfacto)."""

    _target: Type = field(default_factory=lambda: Spars3rNerfstudioDataParser)


def camera_to_worlds_opengl(viewmats: torch.Tensor) -> torch.Tensor:
    """[N, 4, 4] world-to-camera matrices in OpenCV axes -> [N, 3, 4] camera-to-world in nerfstudio's OpenGL axes."""
    camera_to_worlds = torch.linalg.inv(viewmats.double())[:, :3, :4]
    camera_to_worlds[:, :3, :3] *= camera_to_worlds.new_tensor(OPENGL_TO_OPENCV)
    return camera_to_worlds.float()


def to_nerfstudio(outputs: DataparserOutputs) -> NerfstudioOutputs:
    """The project's outputs of one split as nerfstudio's (pinhole cameras; the scene box a cube of half-width the
    scene scale, as nerfstudio's COLMAP parser makes it)."""
    cameras = outputs.cameras
    Ks = cameras.Ks.float()
    metadata = {}
    if outputs.points3d_xyz is not None:
        metadata["points3D_xyz"] = outputs.points3d_xyz.float()
        rgb = outputs.points3d_rgb
        metadata["points3D_rgb"] = rgb if rgb is not None else torch.full_like(outputs.points3d_xyz, 128,
                                                                              dtype=torch.uint8)
    scale = float(outputs.scene_scale)
    return NerfstudioOutputs(
        image_filenames=list(outputs.image_filenames),
        cameras=Cameras(
            camera_to_worlds=camera_to_worlds_opengl(cameras.viewmats),
            fx=Ks[:, 0, 0:1], fy=Ks[:, 1, 1:2], cx=Ks[:, 0, 2:3], cy=Ks[:, 1, 2:3],
            width=cameras.widths.long()[:, None], height=cameras.heights.long()[:, None],
            camera_type=CameraType.PERSPECTIVE,
        ),
        scene_box=SceneBox(aabb=torch.tensor([[-scale] * 3, [scale] * 3], dtype=torch.float32)),
        mask_filenames=list(outputs.mask_filenames) if outputs.mask_filenames else None,
        metadata=metadata,
        dataparser_transform=outputs.dataparser_transform[:3, :4].float(),
        dataparser_scale=float(outputs.dataparser_scale),
    )


class Spars3rNerfstudioDataParser(DataParser):
    """nerfstudio's face of :class:`~kc_splatfacto.data.spars3r.Spars3rDataParser` (one parse serves both splits)."""

    config: Spars3rNerfstudioDataParserConfig

    def __init__(self, config: Spars3rNerfstudioDataParserConfig):
        super().__init__(config)
        self.parser = Spars3rDataParser(config)

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> NerfstudioOutputs:
        return to_nerfstudio(self.parser.get_dataparser_outputs(split))


spars3r = DataParserSpecification(
    config=Spars3rNerfstudioDataParserConfig(),
    description="kc-splatfacto: SPARS3R sparse-view scene (images/, train_list.txt, test_list.txt, COLMAP sparse/0)",
)
