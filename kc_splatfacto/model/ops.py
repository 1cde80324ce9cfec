"""Tensor surgery on Gaussian parameters, with each group's Adam state kept aligned (gsplat's ``strategy/ops.py``).

Every op replaces the parameters in ``params`` (a dict or ParameterDict of [N, ...] tensors) by new Parameters with the
rows selected/added, moves the optimizer state (``exp_avg``, ``exp_avg_sq``; new rows start at zero, Adam's ``step``
is kept) to the new Parameter, and applies the same row operation to every [N, ...] tensor in the strategy ``state``.
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from kc_splatfacto.render.projection import quat_to_rotmat

SPLIT_SCALE_DIVISOR = 1.6
"""a split Gaussian's children have scale / 1.6 (3DGS)"""


@torch.no_grad()
def _update_param_with_optimizer(
    param_fn: Callable[[str, torch.Tensor], torch.nn.Parameter],
    optimizer_fn: Callable[[str, torch.Tensor], torch.Tensor],
    params: dict[str, torch.nn.Parameter] | torch.nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    names: list[str] | None = None,
) -> None:
    names = list(params.keys()) if names is None else names
    for name in names:
        param = params[name]
        new_param = param_fn(name, param)
        params[name] = new_param
        if name not in optimizers:
            continue
        optimizer = optimizers[name]
        for group in optimizer.param_groups:
            param_state = optimizer.state.pop(param, {})
            for key, value in list(param_state.items()):
                if key != "step" and isinstance(value, torch.Tensor) and value.dim() > 0:
                    param_state[key] = optimizer_fn(key, value)
            group["params"] = [new_param]
            if param_state:
                optimizer.state[new_param] = param_state


def _new_param(tensor: torch.Tensor, like: torch.Tensor) -> torch.nn.Parameter:
    return torch.nn.Parameter(tensor.contiguous(), requires_grad=like.requires_grad)


def _kept_rows_then(tensor: torch.Tensor, kept: torch.Tensor, n_new: int) -> torch.Tensor:
    """A new [len(kept) + n_new, ...] tensor whose first rows are ``tensor[kept]`` (gathered once, straight into
    place: ``torch.cat([tensor[kept], new])`` copies every kept row twice); the last ``n_new`` rows are left for the
    caller to fill."""
    out = tensor.new_empty((len(kept) + n_new, *tensor.shape[1:]))
    torch.index_select(tensor, 0, kept, out=out[: len(kept)])
    return out


@torch.no_grad()
def duplicate(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any], mask: torch.Tensor) -> None:
    """Append a copy of every Gaussian where ``mask`` [N] is True (copies go at the end; their Adam state is zero)."""
    sel = torch.where(mask)[0]

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        return _new_param(torch.cat([p, p[sel]]), p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v, torch.zeros((len(sel), *v.shape[1:]), dtype=v.dtype, device=v.device)])

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for key, value in state.items():
        if isinstance(value, torch.Tensor):
            state[key] = torch.cat((value, value[sel]))


@torch.no_grad()
def split(
    params,
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    mask: torch.Tensor,
    n_samples: int = 2,
    revised_opacity: bool = False,
) -> None:
    """Replace every Gaussian where ``mask`` [N] is True by ``n_samples`` children (appended at the end).

    Children's means are drawn from the parent's Gaussian N(mu, R S^2 R^T) (``torch.randn``, so the global RNG
    advances), their scales are the parent's / 1.6, everything else is copied; ``revised_opacity`` uses
    1 - sqrt(1 - o) (Rota Bulo et al.) instead of copying the opacity.
    """
    sel = torch.where(mask)[0]
    rest = torch.where(~mask)[0]
    scales = torch.exp(params["scales"][sel])
    rotmats = quat_to_rotmat(params["quats"][sel])  # normalizes
    noise = torch.randn(n_samples, len(sel), 3, device=scales.device, dtype=scales.dtype)
    samples = torch.einsum("nij,nj,bnj->bni", rotmats, scales, noise)  # [S, M, 3]

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        repeats = [n_samples] + [1] * (p.dim() - 1)
        if name == "means":
            p_split = (p[sel] + samples).reshape(-1, 3)
        elif name == "scales":
            p_split = torch.log(scales / SPLIT_SCALE_DIVISOR).repeat(n_samples, 1)
        elif name == "opacities" and revised_opacity:
            p_split = torch.logit(1.0 - torch.sqrt(1.0 - torch.sigmoid(p[sel]))).repeat(repeats)
        else:
            p_split = p[sel].repeat(repeats)
        out = _kept_rows_then(p, rest, len(p_split))
        out[len(rest):] = p_split
        return _new_param(out, p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        out = _kept_rows_then(v, rest, n_samples * len(sel))
        out[len(rest):] = 0
        return out

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for key, value in state.items():
        if isinstance(value, torch.Tensor):
            repeats = [n_samples] + [1] * (value.dim() - 1)
            state[key] = torch.cat((value[rest], value[sel].repeat(repeats)))


@torch.no_grad()
def remove(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any], mask: torch.Tensor) -> None:
    """Drop every Gaussian where ``mask`` [N] is True."""
    sel = torch.where(~mask)[0]

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        return _new_param(p[sel], p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        return v[sel]

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for key, value in state.items():
        if isinstance(value, torch.Tensor):
            state[key] = value[sel]


@torch.no_grad()
def reset_opa(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any], value: float) -> None:
    """Clamp every opacity to at most ``value`` (in [0, 1]) and zero the opacities' Adam moments."""
    max_logit = torch.logit(torch.tensor(value, dtype=torch.float64)).item()

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        return _new_param(torch.clamp(p, max=max_logit), p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(v)

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers, names=["opacities"])
