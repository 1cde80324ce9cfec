"""How renders and ground truths meet the losses, written once: the layout change (a rasterizer gives [H, W, C] or
[B, H, W, C], the losses take [B, C, H, W]) and an RGBA ground truth composited over the render's background (our
model, ``FrequencyLoss.compare``, kc-render and the figures; the nerfstudio plugin uses nerfstudio's own, which its
main loss reads)."""

from __future__ import annotations

from torch import Tensor


def channels_first(image: Tensor) -> Tensor:
    """[H, W, C] -> [1, C, H, W] and [B, H, W, C] -> [B, C, H, W] (views, no copy).

    >>> import torch
    >>> tuple(channels_first(torch.zeros(4, 6, 3)).shape), tuple(channels_first(torch.zeros(2, 4, 6, 3)).shape)
    ((1, 3, 4, 6), (2, 3, 4, 6))
    """
    return image.permute(2, 0, 1)[None] if image.dim() == 3 else image.permute(0, 3, 1, 2)


def composite_with_background(
    image: Tensor, background: Tensor, premultiplied: bool = False
) -> Tensor:
    """[..., H, W, 4] RGBA -> [..., H, W, 3] ``rgb * a + background * (1 - a)`` (``rgb`` already times ``a`` when
    ``premultiplied``); [..., H, W, 3] is returned as is. ``background``: [3].

    nerfstudio's ``composite_with_background``: the GT is composited over the background the render used.

    >>> import torch
    >>> half_clear_red = torch.tensor([[[1.0, 0.0, 0.0, 0.5]]])
    >>> composite_with_background(half_clear_red, torch.tensor([0.0, 0.0, 1.0])).tolist()
    [[[0.5, 0.0, 0.5]]]
    """
    if image.shape[-1] == 3:
        return image
    if image.shape[-1] != 4:
        raise ValueError(f"ground truth must be [..., H, W, 3] or [..., H, W, 4] (RGBA), got {tuple(image.shape)}")
    alpha = image[..., 3:4]
    rgb = image[..., :3] if premultiplied else image[..., :3] * alpha
    return rgb + background.to(image) * (1.0 - alpha)
