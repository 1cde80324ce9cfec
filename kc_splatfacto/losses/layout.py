"""The one layout change between renders and losses: a rasterizer gives [H, W, C] (or [B, H, W, C]), the losses take
[B, C, H, W]."""

from __future__ import annotations

from torch import Tensor


def channels_first(image: Tensor) -> Tensor:
    """[H, W, C] -> [1, C, H, W] and [B, H, W, C] -> [B, C, H, W] (views, no copy).

    >>> import torch
    >>> tuple(channels_first(torch.zeros(4, 6, 3)).shape), tuple(channels_first(torch.zeros(2, 4, 6, 3)).shape)
    ((1, 3, 4, 6), (2, 3, 4, 6))
    """
    return image.permute(2, 0, 1)[None] if image.dim() == 3 else image.permute(0, 3, 1, 2)
