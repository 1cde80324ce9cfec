"""What every dataparser returns: one :class:`DataparserOutputs` per split.

Conventions (shared by every layer below the data layer):
- ``viewmats`` are world-to-camera 4x4 matrices in OpenCV axes (x right, y down, z forward), the convention of
  gsplat's ``rasterization``; worlds are already normalized (see ``dataparser_transform``/``dataparser_scale``).
- ``Ks`` are pinhole intrinsics in pixels for the (possibly downscaled) image size, pixel centres at +0.5.
- Distorted images are undistorted by the parser, so cameras here are always plain pinhole.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch


@dataclass
class Cameras:
    """A batch of pinhole cameras.

    Attributes:
        viewmats: [N, 4, 4] float32 world-to-camera, OpenCV axes.
        Ks: [N, 3, 3] float32 intrinsics.
        widths: [N] int64 image widths in pixels.
        heights: [N] int64 image heights in pixels.
    """

    viewmats: torch.Tensor
    Ks: torch.Tensor
    widths: torch.Tensor
    heights: torch.Tensor

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def __getitem__(self, index: Any) -> "Cameras":
        """Cameras subset; an int index keeps the batch dimension ([1, ...])."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return Cameras(self.viewmats[index], self.Ks[index], self.widths[index], self.heights[index])

    def camera_to_worlds(self) -> torch.Tensor:
        """[N, 4, 4] camera-to-world matrices (OpenCV axes)."""
        return torch.linalg.inv(self.viewmats)

    def centers(self) -> torch.Tensor:
        """[N, 3] camera centres in world coordinates."""
        return self.camera_to_worlds()[:, :3, 3]

    def to(self, device: torch.device | str) -> "Cameras":
        return Cameras(self.viewmats.to(device), self.Ks.to(device), self.widths.to(device), self.heights.to(device))


@dataclass
class DataparserOutputs:
    """One split of a scene, ready for a dataset.

    Attributes:
        image_filenames: one image file per camera (only the split's images; nothing else is read).
        cameras: the split's cameras, in the normalized world.
        split: "train", "val" or "test".
        scene_scale: half-width of the origin-centred cube holding every normalized camera centre (train and eval):
            1.0 whenever poses are auto-scaled (nerfstudio's ``auto_scale_poses``, the default), i.e. the unit in
            which Splatfacto's size thresholds (densify/split/cull sizes, random init extent) are expressed; those
            thresholds are multiplied by it.
        dataparser_transform: [3, 4] float32, the transform applied to the original poses (before scaling): an
            original world point ``p`` is at ``dataparser_scale * (dataparser_transform @ [p, 1])`` here
            (nerfstudio's ``dataparser_transforms.json``; see ``kc_splatfacto.data.write_dataparser_transforms``).
        dataparser_scale: scale factor applied after ``dataparser_transform``.
        points3d_xyz: [M, 3] float32 seed points in the normalized world, or None.
        points3d_rgb: [M, 3] uint8 colours of the seed points, or None.
        mask_filenames: optional per-image masks (alpha kept as mask), or None.
        metadata: parser-specific extras (e.g. the source format, skipped names).
    """

    image_filenames: list[Path]
    cameras: Cameras
    split: str
    scene_scale: float = 1.0
    dataparser_transform: torch.Tensor = field(default_factory=lambda: torch.eye(4)[:3])
    dataparser_scale: float = 1.0
    points3d_xyz: torch.Tensor | None = None
    points3d_rgb: torch.Tensor | None = None
    mask_filenames: list[Path] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
