"""Image-quality metrics on [B, 3, H, W] images in [0, 1].

``lpips(pred, gt, net="alex")``: LPIPS v0.1 (see :mod:`kc_splatfacto.lpips`).
"""

from kc_splatfacto.lpips import lpips

__all__ = ["lpips"]
