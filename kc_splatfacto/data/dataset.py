"""Images of one split, decoded lazily and kept as uint8 (nerfstudio's ``cache_images_type="uint8"``).

Only the split's files are ever read; each image is decoded on first access and cached. RGBA images are composited
over ``background`` (in [0,1], per channel) and their alpha is kept as a mask when ``alpha_as_mask`` is set; masks
from ``DataparserOutputs.mask_filenames`` take precedence.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.images import read_image
from kc_splatfacto.data.outputs import Cameras, DataparserOutputs


def composite_over_background(rgba: np.ndarray, background: Sequence[float]) -> np.ndarray:
    """[H,W,4] uint8 -> [H,W,3] uint8: ``rgb * a + background * (1 - a)`` in float, rounded to nearest."""
    rgb = rgba[..., :3].astype(np.float32) / 255.0
    alpha = rgba[..., 3:4].astype(np.float32) / 255.0
    out = rgb * alpha + np.asarray(background, np.float32) * (1.0 - alpha)
    return np.round(np.clip(out, 0.0, 1.0) * 255.0).astype(np.uint8)


class ImageDataset:
    """The split's images and cameras.

    Args:
        outputs: one split of a dataparser.
        background: RGB in [0,1] that RGBA images are composited over.
        alpha_as_mask: keep the alpha channel of RGBA images as a [H,W,1] bool mask (alpha > 0.5).
    """

    def __init__(
        self,
        outputs: DataparserOutputs,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        alpha_as_mask: bool = False,
    ):
        if len(outputs.image_filenames) != len(outputs.cameras):
            raise DataParserError(
                f"{len(outputs.image_filenames)} image files but {len(outputs.cameras)} cameras in split "
                f"'{outputs.split}': the dataparser must return one camera per image"
            )
        if len(background) != 3 or not all(0.0 <= float(c) <= 1.0 for c in background):
            raise DataParserError(f"background must be 3 values in [0, 1], got {tuple(background)}")
        self.outputs = outputs
        self.background = tuple(float(c) for c in background)
        self.alpha_as_mask = alpha_as_mask
        self._images: dict[int, torch.Tensor] = {}
        self._masks: dict[int, torch.Tensor | None] = {}

    def __len__(self) -> int:
        return len(self.outputs.image_filenames)

    @property
    def cameras(self) -> Cameras:
        return self.outputs.cameras

    @property
    def split(self) -> str:
        return self.outputs.split

    @property
    def image_filenames(self):
        return self.outputs.image_filenames

    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"image index {i} out of range for the {n} images of split '{self.split}'")
        return i % n

    def _load(self, i: int) -> None:
        path = self.outputs.image_filenames[i]
        image = read_image(path)
        width, height = int(self.cameras.widths[i]), int(self.cameras.heights[i])
        if image.shape[:2] != (height, width):
            raise DataParserError(
                f"image {path} is {image.shape[1]}x{image.shape[0]} but its camera expects {width}x{height}: "
                "the file changed since parsing or belongs to another camera"
            )
        mask = None
        if image.shape[2] == 4:
            if self.alpha_as_mask:
                mask = torch.from_numpy(image[..., 3:4] > 127)
            image = composite_over_background(image, self.background)
        if self.outputs.mask_filenames is not None:
            mask_path = self.outputs.mask_filenames[i]
            mask_image = read_image(mask_path)
            if mask_image.shape[:2] != (height, width):
                raise DataParserError(
                    f"mask {mask_path} is {mask_image.shape[1]}x{mask_image.shape[0]}, expected {width}x{height}"
                )
            mask = torch.from_numpy(mask_image[..., :1] > 127)
        self._images[i] = torch.from_numpy(np.ascontiguousarray(image))
        self._masks[i] = mask

    def image_uint8(self, i: int) -> torch.Tensor:
        """[H,W,3] uint8 image ``i`` (decoded on first use, then cached)."""
        i = self._index(i)
        if i not in self._images:
            self._load(i)
        return self._images[i]

    def image_float(self, i: int) -> torch.Tensor:
        """[H,W,3] float32 image ``i`` in [0,1]."""
        return self.image_uint8(i).to(torch.float32) / 255.0

    def mask(self, i: int) -> torch.Tensor | None:
        """[H,W,1] bool mask of image ``i`` (True = use the pixel), or None when the image has none."""
        i = self._index(i)
        if i not in self._images:
            self._load(i)
        return self._masks[i]

    def __getitem__(self, i: int) -> dict:
        """nerfstudio-style item: ``{"image_idx", "image" (uint8 [H,W,3]), "mask" (optional)}``."""
        item = {"image_idx": self._index(i), "image": self.image_uint8(i)}
        mask = self.mask(i)
        if mask is not None:
            item["mask"] = mask
        return item

    def num_loaded(self) -> int:
        """How many images have been decoded so far (images are loaded lazily)."""
        return len(self._images)
