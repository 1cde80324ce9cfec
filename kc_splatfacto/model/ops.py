"""Tensor surgery on Gaussian parameters, with each group's Adam state kept aligned (gsplat's ``strategy/ops.py``).

Every op replaces the parameters in ``params`` (a dict or ParameterDict of [N, ...] tensors) by new Parameters with the
rows selected/added, moves the optimizer state (``exp_avg``, ``exp_avg_sq``; new rows start at zero, Adam's ``step``
is kept) to the new Parameter, and applies the same row operation to every [N, ...] tensor in the strategy ``state``.

``relocate``, ``sample_add`` and ``inject_noise_to_position`` are MCMC densification's (gsplat 1.5.3's ops of the same
names): copies of Gaussians drawn by opacity, each source's opacity and scale shared among its copies
(:mod:`kc_splatfacto.model.relocation`), and the means' exploration noise.
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from kc_splatfacto.model.relocation import compute_relocation
from kc_splatfacto.render.projection import quat_to_rotmat

SPLIT_SCALE_DIVISOR = 1.6
"""a split Gaussian's children have scale / 1.6 (3DGS)"""
MULTINOMIAL_MAX_CATEGORIES = 2**24
"""torch.multinomial draws from at most 2^24 categories; beyond, an inverse-CDF draw (gsplat falls back to numpy)"""
NOISE_GATE_SHARPNESS = 100.0
NOISE_GATE_CENTER = 0.995
"""the noise gate sigmoid(100 ((1 - opacity) - 0.995)): ~1 for opacity below ~0.005, ~0 for visible Gaussians"""


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


@torch.no_grad()
def sample_by_weight(weights: torch.Tensor, n: int) -> torch.Tensor:
    """[n] int64 indices into ``weights`` [N] (non-negative, not all zero), drawn with replacement in proportion to
    them (torch's global RNG)."""
    if len(weights) <= MULTINOMIAL_MAX_CATEGORIES:
        return torch.multinomial(weights, n, replacement=True)
    cumulative = torch.cumsum(weights.to(torch.float64), 0)
    draws = torch.rand(n, dtype=torch.float64, device=weights.device) * cumulative[-1]
    return torch.searchsorted(cumulative, draws, right=True).clamp_max(len(weights) - 1)


def _shared_among_copies(params, opacities: torch.Tensor, sampled: torch.Tensor,
                         min_opacity: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The new (logit opacity [M], log scale [M, 3]) of each sampled source: its opacity and scale shared among
    itself and the copies made of it (as many as it was drawn), the opacity kept in [min_opacity, 1 - eps]."""
    copies = torch.bincount(sampled, minlength=len(opacities))[sampled] + 1
    new_opacities, new_scales = compute_relocation(opacities[sampled], torch.exp(params["scales"].detach()[sampled]),
                                                   copies)
    new_opacities = new_opacities.clamp(min=min_opacity, max=1.0 - torch.finfo(torch.float32).eps)
    return torch.logit(new_opacities), torch.log(new_scales)


def _with_sources_updated(name: str, p: torch.Tensor, sampled: torch.Tensor, logit_opacities: torch.Tensor,
                          log_scales: torch.Tensor) -> torch.Tensor:
    """A copy of parameter ``p`` [N, ...] whose sampled rows hold their shared opacity or scale."""
    out = p.detach().clone()
    if name == "opacities":
        out[sampled] = logit_opacities.reshape(out[sampled].shape).to(out.dtype)
    elif name == "scales":
        out[sampled] = log_scales.to(out.dtype)
    return out


@torch.no_grad()
def relocate(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any], mask: torch.Tensor,
             min_opacity: float) -> int:
    """Move every dead Gaussian (``mask`` [N] True) onto a live one drawn in proportion to opacity: the source's
    opacity and scale are shared among it and its copies, and each dead row becomes a copy of its source (the count
    stays N). As gsplat does, the sources' Adam moments and ``state`` rows are zeroed (their opacity and scale
    changed); the dead rows keep theirs. Returns how many were moved (0 when none is dead or none is alive)."""
    opacities = torch.sigmoid(params["opacities"].detach().flatten())
    dead = torch.where(mask)[0]
    alive = torch.where(~mask)[0]
    if len(dead) == 0 or len(alive) == 0:
        return 0
    sampled = alive[sample_by_weight(opacities[alive], len(dead))]
    logit_opacities, log_scales = _shared_among_copies(params, opacities, sampled, min_opacity)

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        out = _with_sources_updated(name, p, sampled, logit_opacities, log_scales)
        out[dead] = out[sampled]
        return _new_param(out, p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        v = v.clone()
        v[sampled] = 0
        return v

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for value in state.values():
        if isinstance(value, torch.Tensor):
            value[sampled] = 0
    return len(dead)


@torch.no_grad()
def sample_add(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any], n: int,
               min_opacity: float) -> None:
    """Append ``n`` copies of Gaussians drawn in proportion to opacity (with replacement); each source's opacity
    and scale are shared among it and its copies. The copies' Adam moments and ``state`` rows start at zero."""
    opacities = torch.sigmoid(params["opacities"].detach().flatten())
    sampled = sample_by_weight(opacities, n)
    logit_opacities, log_scales = _shared_among_copies(params, opacities, sampled, min_opacity)

    def param_fn(name: str, p: torch.Tensor) -> torch.nn.Parameter:
        out = _with_sources_updated(name, p, sampled, logit_opacities, log_scales)
        return _new_param(torch.cat([out, out[sampled]]), p)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v, v.new_zeros((len(sampled), *v.shape[1:]))])

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for key, value in state.items():
        if isinstance(value, torch.Tensor):
            state[key] = torch.cat([value, value.new_zeros((len(sampled), *value.shape[1:]))])


@torch.no_grad()
def inject_noise_to_position(params, optimizers: dict[str, torch.optim.Optimizer], state: dict[str, Any],
                             scaler: float, factor: torch.Tensor | None = None) -> None:
    """Add to every mean Sigma g(o) ``scaler`` z: z ~ N(0, I) [N, 3] (torch's global RNG), Sigma = R S^2 R^T the
    Gaussian's covariance, g(o) = sigmoid(100 ((1 - o) - 0.995)) its noise gate (near 1 only for nearly transparent
    Gaussians), times ``factor`` (a device scalar, 1 or 0: applied without reading it) when given. In place: the
    Parameter and its Adam moments stay."""
    opacities = torch.sigmoid(params["opacities"].detach().flatten())
    variances = torch.exp(2.0 * params["scales"].detach())  # S^2
    rotmats = quat_to_rotmat(params["quats"].detach())  # normalizes
    gate = torch.sigmoid(NOISE_GATE_SHARPNESS * ((1.0 - opacities) - NOISE_GATE_CENTER))
    means = params["means"]
    noise = torch.randn_like(means) * gate[:, None] * scaler
    if factor is not None:
        noise = noise * factor  # x 1 is exact: a good step's noise is the host verdict's bit for bit
    # Sigma z as R (S^2 (R^T z)): two matrix-vector products per Gaussian, no [N, 3, 3] covariance
    in_local_axes = torch.einsum("nji,nj->ni", rotmats, noise) * variances
    means.add_(torch.einsum("nij,nj->ni", rotmats, in_local_axes))
