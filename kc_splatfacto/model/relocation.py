"""The opacity and scale of a Gaussian split among copies of itself, as MCMC densification relocates and adds them
("3D Gaussian Splatting as Markov Chain Monte Carlo", Kheradmand et al. 2024, eq. 9; gsplat's
``compute_relocation``).

A Gaussian of opacity o and scales s that becomes n Gaussians at the same place (itself and n - 1 copies) gives
each of them

    o' = 1 - (1 - o)^(1/n)                                  (the n copies composite to o)
    s' = o / (sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)) * s

On CUDA gsplat's kernel computes it when gsplat is installed; elsewhere :func:`relocation_torch` does, with the
double sum folded into one (sum_{i=k+1..n} C(i-1, k) = C(n, k+1), the hockey-stick identity) and in float64: the
alternating sum cancels terms up to 1 / (1 - o) in size, which float32 would leave with few correct digits.
"""

from __future__ import annotations

import functools
import inspect
import math

import torch

MAX_COPIES = 51
"""gsplat's ``n_max``: the number of copies a Gaussian's share is computed for is clamped to [1, 51]"""


@functools.lru_cache(maxsize=None)
def binomial_table(rows: int = MAX_COPIES, dtype: torch.dtype = torch.float64, device: str = "cpu") -> torch.Tensor:
    """[rows, rows] C(n, k) (0 where k > n): gsplat's ``binoms`` (float32, ``rows`` = 51) and, one row longer, this
    module's float64 table. Cached per device: it is a constant, not per-run state."""
    table = torch.zeros(rows, rows, dtype=torch.float64)
    for n in range(rows):
        for k in range(n + 1):
            table[n, k] = math.comb(n, k)
    return table.to(dtype=dtype, device=device)


def relocation_torch(opacities: torch.Tensor, scales: torch.Tensor, ratios: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The module docstring's o' [M] and s' [M, 3] from opacities [M] (in (0, 1)), scales [M, 3] (positive) and
    ratios [M] (the number of Gaussians each one becomes, clamped to [1, MAX_COPIES]), in the inputs' dtype."""
    if len(ratios) == 0:
        return opacities.clone(), scales.clone()
    n = ratios.clamp(1, MAX_COPIES).to(torch.int64)
    o = opacities.to(torch.float64)
    new_o = 1.0 - (1.0 - o) ** (1.0 / n.to(torch.float64))
    terms = int(n.max())
    j = torch.arange(1, terms + 1, dtype=torch.float64, device=o.device)
    table = binomial_table(MAX_COPIES + 1, torch.float64, str(o.device))
    signs = torch.where(j.remainder(2) == 1, 1.0, -1.0)  # (-1)^(j-1)
    coefficients = table[n][:, 1:terms + 1] * signs / torch.sqrt(j)  # C(n, j) (-1)^(j-1) / sqrt(j), 0 for j > n
    denominator = (coefficients * new_o[:, None] ** j).sum(dim=-1)
    new_scales = (o / denominator)[:, None] * scales.to(torch.float64)
    return new_o.to(opacities.dtype), new_scales.to(scales.dtype)


def _gsplat_relocation():
    """gsplat's ``compute_relocation``, or None when gsplat is not installed (or fails to import)."""
    try:
        from gsplat.relocation import compute_relocation
    except Exception:  # ImportError, or a CUDA build failing at import: the torch formula then
        return None
    return compute_relocation


def compute_relocation(opacities: torch.Tensor, scales: torch.Tensor, ratios: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """o' [M] and s' [M, 3] (module docstring): gsplat's kernel for float32 CUDA tensors when gsplat is installed,
    :func:`relocation_torch` otherwise."""
    if len(opacities) > 0 and opacities.is_cuda and opacities.dtype == torch.float32:
        gsplat_relocation = _gsplat_relocation()
        if gsplat_relocation is not None:
            binoms = binomial_table(MAX_COPIES, torch.float32, str(opacities.device))
            kwargs = {"n_max": MAX_COPIES} if "n_max" in inspect.signature(gsplat_relocation).parameters else {}
            new_opacities, new_scales = gsplat_relocation(opacities=opacities.contiguous(), scales=scales.contiguous(),
                                                          ratios=ratios.clone(), binoms=binoms, **kwargs)
            # the kernel writes the scales as [3 M] (some gsplat versions return them so)
            return new_opacities.reshape(-1), new_scales.reshape(-1, 3)
    return relocation_torch(opacities, scales, ratios)
