"""Images of one split, decoded lazily and kept as uint8 (nerfstudio's ``cache_images_type="uint8"``).

Only the split's files are ever read; each image is decoded on first access and cached. RGBA images keep their alpha
channel: the model composites them over the background it renders with (nerfstudio's ``composite_with_background``),
which the data layer cannot know. Masks come from ``DataparserOutputs.mask_filenames``.
"""

from __future__ import annotations

import numpy as np
import torch

from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.images import read_image
from kc_splatfacto.data.outputs import Cameras, DataparserOutputs


class ImageDataset:
    """The split's images, masks and cameras.

    Args:
        outputs: one split of a dataparser.
    """

    def __init__(self, outputs: DataparserOutputs):
        if len(outputs.image_filenames) != len(outputs.cameras):
            raise DataParserError(
                f"{len(outputs.image_filenames)} image files but {len(outputs.cameras)} cameras in split "
                f"'{outputs.split}': the dataparser must return one camera per image"
            )
        self.outputs = outputs
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
        """[H,W,C] uint8 image ``i``, C = 3 (RGB) or 4 (RGBA, straight alpha); decoded on first use, then cached."""
        i = self._index(i)
        if i not in self._images:
            self._load(i)
        return self._images[i]

    def image_float(self, i: int) -> torch.Tensor:
        """[H,W,C] float32 image ``i`` in [0,1] (C as :meth:`image_uint8`)."""
        return self.image_uint8(i).to(torch.float32) / 255.0

    def mask(self, i: int) -> torch.Tensor | None:
        """[H,W,1] bool mask of image ``i`` (True = use the pixel), or None when the image has none."""
        i = self._index(i)
        if i not in self._images:
            self._load(i)
        return self._masks[i]

    def __getitem__(self, i: int) -> dict:
        """nerfstudio's item, the batch the model reads: ``image_idx``, ``image`` (uint8 [H,W,3|4]) and ``mask``
        ([H,W,1] bool, only when the split has masks)."""
        item = {"image_idx": self._index(i), "image": self.image_uint8(i)}
        mask = self.mask(i)
        if mask is not None:
            item["mask"] = mask
        return item

    def num_loaded(self) -> int:
        """How many images have been decoded so far (images are loaded lazily)."""
        return len(self._images)
