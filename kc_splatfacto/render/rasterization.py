"""``rasterization()``: gsplat 1.5.3's call and return contract (unpacked, pinhole), with three rasterizers.

:func:`rasterization` checks the request (:func:`resolve_rasterizer`) and hands it to one function per rasterizer
(its ``rasterizer`` argument; the model config's field of the same name):

- ``"torch"`` (:func:`_rasterization_torch`): the reference, every stage in torch ops (projection, SH, tile binning,
  :func:`rasterize_to_pixels_torch`), differentiable by autograd; slow; the tests' oracle.
- ``"cpu"`` (:func:`_rasterization_cpu`): compiled numba kernels with hand-written backward passes: projection and SH
  in one pass (``project_cpu``; float32/float64 inputs, the torch projection for other dtypes), tile binning
  (``tiles.bin_tiles_cpu``), compositing (``rasterize_cpu.rasterize_to_pixels_cpu``).
- ``"gsplat"`` (:func:`_rasterization_gsplat`): ``gsplat.rasterization`` itself; needs gsplat and CUDA tensors.
- ``"auto"``: gsplat for CUDA tensors (an error when gsplat is missing), cpu for CPU tensors, or torch when the
  reference is forced (:mod:`kc_splatfacto.backend`, the one switch between every compiled kernel and its torch
  reference: ``KC_SPLATFACTO_BACKEND=torch`` or ``backend.torch_reference()``; a debugging switch, not a choice of
  rasterizer).

The cpu and torch rasterizers share the tail (:func:`_composite`: render-mode channels, binning, compositing, meta).
"""

from __future__ import annotations

import warnings
from typing import Callable, Literal, Optional

import torch
from torch import Tensor

from kc_splatfacto import backend

from .constants import EPS2D, EXPECTED_DEPTH_ALPHA_MIN, FAR_PLANE, NEAR_PLANE, TILE_SIZE
from .non_finite import NonFiniteInputError, non_finite_message
from .projection import ProjectedSplats, fully_fused_projection
from .rasterize_torch import rasterize_to_pixels_torch
from .sh import SplitSH, sh_to_rgb
from .tiles import bin_tiles_cpu, isect_offset_encode, isect_tiles, tile_grid

RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
RasterizeMode = Literal["classic", "antialiased"]
Rasterizer = Literal["auto", "cpu", "torch", "gsplat"]
RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")
RASTERIZERS = ("auto", "cpu", "torch", "gsplat")


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA build raising at import
        return False
    return True


def _cpu_rasterizer() -> Optional[Callable]:
    try:
        from .rasterize_cpu import rasterize_to_pixels_cpu
    except ImportError:
        return None
    return rasterize_to_pixels_cpu


def resolve_rasterizer(rasterizer: str, device: torch.device) -> str:
    """The concrete rasterizer for ``rasterizer`` and tensors on ``device``; raises on impossible requests. "auto"
    gives "torch" while the reference is forced (:mod:`kc_splatfacto.rasterizer`); an explicit choice is always
    honoured.

    Raises:
        ValueError: unknown rasterizer, or "cpu" asked with non-CPU tensors.
        RuntimeError: "gsplat" asked without gsplat or without CUDA tensors, or "auto" with CUDA tensors and no
            gsplat (never a silent fallback).
        ImportError: "cpu" asked while the compiled module cannot be imported.
    """
    if rasterizer not in RASTERIZERS:
        raise ValueError(f"rasterizer must be one of {RASTERIZERS}, got {rasterizer!r}")
    if rasterizer == "auto":
        if backend.reference_forced():
            return "torch"
        if device.type == "cuda":
            if _gsplat_available():
                return "gsplat"
            raise RuntimeError(
                "rasterization(rasterizer='auto') got CUDA tensors but gsplat is not installed: install gsplat==1.5.3, "
                "move the tensors to the CPU (compiled cpu rasterizer), or pass rasterizer='torch' (slow reference)"
            )
        if _cpu_rasterizer() is not None:
            return "cpu"
        warnings.warn(
            "rasterization(rasterizer='auto'): the compiled cpu rasterizer (kc_splatfacto.render.rasterize_cpu) is not "
            "available; using the slow torch reference",
            RuntimeWarning,
            stacklevel=3,
        )
        return "torch"
    if rasterizer == "gsplat":
        if not _gsplat_available():
            raise RuntimeError(
                "rasterization(rasterizer='gsplat') needs the gsplat package (pip install gsplat==1.5.3, with CUDA); "
                "use rasterizer='cpu' or 'auto' on machines without it"
            )
        if device.type != "cuda":
            raise RuntimeError(
                f"rasterization(rasterizer='gsplat') needs CUDA tensors, got tensors on {device}; "
                "move them with .cuda() or use rasterizer='cpu'"
            )
        return "gsplat"
    if rasterizer == "cpu":
        if device.type != "cpu":
            raise ValueError(f"rasterization(rasterizer='cpu') needs CPU tensors, got {device}; use rasterizer='gsplat'")
        if _cpu_rasterizer() is None:
            raise ImportError(
                "rasterization(rasterizer='cpu'): kc_splatfacto.render.rasterize_cpu (numba kernels) is not available; "
                "install numba or use rasterizer='torch'"
            )
    return rasterizer


def _match_numba_threads() -> None:
    """Run numba's parallel loops on as many threads as torch uses (never more), so the two pools, which take turns
    within a step, do not oversubscribe the cores; both follow ``torch.set_num_threads``."""
    import numba

    wanted = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
    if numba.get_num_threads() != wanted:
        numba.set_num_threads(wanted)


def _check_inputs(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor | SplitSH,  # SplitSH only on the fused cpu path (its shape is checked here)
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: Optional[int],
    backgrounds: Optional[Tensor],
    render_mode: str,
    rasterize_mode: str,
    check_finite: bool = True,
) -> None:
    """Shapes and options; with ``check_finite`` also a full NaN/inf pass over every input (the torch reference's
    path; the compiled path finds non-finite values inside its projection kernel instead)."""
    if means.dim() != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    if quats.shape != (n, 4):
        raise ValueError(f"quats must be [N, 4] = [{n}, 4] (wxyz), got {tuple(quats.shape)}")
    if scales.shape != (n, 3):
        raise ValueError(f"scales must be [N, 3] = [{n}, 3] (linear, not log), got {tuple(scales.shape)}")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must be [N] = [{n}] in [0, 1] (not logits, no trailing 1), got {tuple(opacities.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4] world-to-camera, got {tuple(viewmats.shape)}")
    c = viewmats.shape[0]
    if Ks.shape != (c, 3, 3):
        raise ValueError(f"Ks must be [C, 3, 3] = [{c}, 3, 3], got {tuple(Ks.shape)}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"width and height must be positive integers, got width={width}, height={height}")
    if sh_degree is None:
        dim = len(colors.shape)
        if not (dim == 2 and colors.shape[0] == n) and not (dim == 3 and colors.shape[:2] == (c, n)):
            raise ValueError(
                f"colors must be [N, D] or [C, N, D] (N={n}, C={c}) when sh_degree is None, got {tuple(colors.shape)}; "
                "pass sh_degree for SH coefficients [N, K, 3]"
            )
    else:
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        shape = colors.shape
        ok = (len(shape) == 3 and shape[0] == n) or (len(shape) == 4 and shape[:2] == (c, n))
        if not ok or shape[-1] != 3 or shape[-2] < (sh_degree + 1) ** 2:
            raise ValueError(
                f"SH colors must be [N, K, 3] or [C, N, K, 3] with K >= (sh_degree + 1)^2 = {(sh_degree + 1) ** 2}, "
                f"got {tuple(shape)}"
            )
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if backgrounds is not None and (backgrounds.dim() != 2 or backgrounds.shape[0] != c):
        raise ValueError(f"backgrounds must be [C, D] with C={c}, got {tuple(backgrounds.shape)}")
    if not check_finite:
        return
    for name, tensor in (
        ("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities),
        ("colors", colors if isinstance(colors, Tensor) else colors.cat()), ("viewmats", viewmats), ("Ks", Ks),
    ):
        if not torch.isfinite(tensor).all():
            raise NonFiniteInputError(non_finite_message(name, tensor), (name,))


def rasterization(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor | SplitSH,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int] = None,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
    radius_clip: float = 0.0,
    backgrounds: Optional[Tensor] = None,
    render_mode: RenderMode = "RGB",
    rasterize_mode: RasterizeMode = "classic",
    absgrad: bool = False,
    tile_size: int = TILE_SIZE,
    rasterizer: Rasterizer = "auto",
) -> tuple[Tensor, Tensor, dict]:
    """Render N Gaussians into C pinhole cameras (gsplat 1.5.3 ``rasterization``, packed=False).

    Args:
        means: [N, 3]; quats: [N, 4] wxyz, any norm; scales: [N, 3] linear; opacities: [N] in [0, 1].
        colors: [N, D] or [C, N, D] post-activation, or SH coefficients [N, K, 3] / [C, N, K, 3] with ``sh_degree``
            (colour = max(SH(means - camera centre) + 0.5, 0)), or those coefficients as a :class:`sh.SplitSH`
            (degree 0 and the rest in two tensors, as Splatfacto holds them: the cpu rasterizer reads them in place;
            the others concatenate them).
        viewmats: [C, 4, 4] world-to-camera (OpenCV); Ks: [C, 3, 3]; width, height: pixels.
        render_mode: "RGB"; "D" accumulated depth; "ED" expected depth (accumulated depth / max(alpha, 1e-10));
            "RGB+D", "RGB+ED": depth as an extra last channel (background 0 for it).
        rasterize_mode: "antialiased" multiplies opacities by the eps2d compensation.
        absgrad: fill ``meta["means2d"].absgrad`` in backward.
        rasterizer: "auto" | "cpu" | "torch" | "gsplat" (see the module docstring).

    Returns:
        render_colors [C, H, W, ch], render_alphas [C, H, W, 1], meta (``means2d`` [C, N, 2] whose ``.grad`` backward
        fills, ``radii`` [C, N, 2] int32, ``depths`` [C, N], ``conics``, ``opacities`` [C, N], tile data, ``width``,
        ``height``, ``tile_size``, ``n_cameras``, ``rasterizer``).
    """
    resolved = resolve_rasterizer(rasterizer, means.device)
    if isinstance(colors, SplitSH):
        # checked once here; only the cpu rasterizer's compiled projection reads the two tensors in place
        if sh_degree is None:
            raise ValueError("colors=SplitSH(...) holds SH coefficients: pass sh_degree")
        colors.check()
        if not (resolved == "cpu" and _compiled_projection(means)):
            colors = colors.cat()
    options = dict(
        sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, radius_clip=radius_clip,
        backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode, absgrad=absgrad,
        tile_size=tile_size,
    )
    if resolved == "gsplat":
        return _rasterization_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options)
    if resolved == "cpu":
        return _rasterization_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options)
    return _rasterization_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options)


def _compiled_projection(means: Tensor) -> bool:
    """The cpu rasterizer projects with its compiled kernel for float32/float64 (other dtypes: the torch projection)."""
    return means.dtype in (torch.float32, torch.float64)


def _rasterization_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                          near_plane, far_plane, eps2d, radius_clip, backgrounds, render_mode, rasterize_mode,
                          absgrad, tile_size) -> tuple[Tensor, Tensor, dict]:
    """``gsplat.rasterization`` itself (CUDA tensors), with ``meta["means2d"]`` keeping its gradient."""
    import gsplat  # optional: resolve_rasterizer checked that it imports

    render_colors, render_alphas, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, radius_clip=radius_clip, sh_degree=sh_degree,
        tile_size=tile_size, backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
        absgrad=absgrad, packed=False,
    )
    if meta["means2d"].requires_grad:
        meta["means2d"].retain_grad()
    meta["rasterizer"] = "gsplat"
    return render_colors, render_alphas, meta


def _rasterization_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                       near_plane, far_plane, eps2d, radius_clip, backgrounds, render_mode, rasterize_mode, absgrad,
                       tile_size) -> tuple[Tensor, Tensor, dict]:
    """The compiled CPU path: projection and SH in one kernel (float32/float64 inputs; the torch projection for
    other dtypes), compiled tile binning, compiled compositing."""
    fused = _compiled_projection(means)
    _check_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds, render_mode,
        rasterize_mode, check_finite=not fused,  # the compiled projection finds NaN/inf while it reads its inputs
    )
    width, height = int(width), int(height)
    if fused:
        splats = _project_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                              near_plane, far_plane, eps2d, radius_clip, rasterize_mode)
    else:
        splats = _project_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                                near_plane, far_plane, eps2d, radius_clip, rasterize_mode)

    from .rasterize_cpu import rasterize_to_pixels_cpu  # numba: loaded with the first cpu render

    def bin_tiles(means2d, radii, depths, tile_width, tile_height):
        return bin_tiles_cpu(means2d, radii, depths, tile_size, tile_width, tile_height)

    return _composite(splats, width, height, backgrounds, render_mode, absgrad, tile_size, bin_tiles,
                      rasterize_to_pixels_cpu, "cpu")


def _rasterization_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, sh_degree,
                         near_plane, far_plane, eps2d, radius_clip, backgrounds, render_mode, rasterize_mode, absgrad,
                         tile_size) -> tuple[Tensor, Tensor, dict]:
    """The torch reference: every stage in torch ops, differentiated by autograd (the tests' oracle)."""
    _check_inputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds, render_mode,
        rasterize_mode,
    )
    width, height = int(width), int(height)
    splats = _project_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
                            near_plane, far_plane, eps2d, radius_clip, rasterize_mode)

    def bin_tiles(means2d, radii, depths, tile_width, tile_height):
        n_cameras = means2d.shape[0]
        tiles_per_gauss, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tile_width,
                                                              tile_height)
        return tiles_per_gauss, isect_ids, flatten_ids, isect_offset_encode(isect_ids, n_cameras, tile_width,
                                                                            tile_height)

    return _composite(splats, width, height, backgrounds, render_mode, absgrad, tile_size, bin_tiles,
                      rasterize_to_pixels_torch, "torch")


def _project_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, near_plane,
                 far_plane, eps2d, radius_clip, rasterize_mode) -> ProjectedSplats:
    """Compiled projection and SH colours; per-pair colours [C, N, D] filled in either way."""
    from .project_cpu import project_and_shade_cpu

    _match_numba_threads()
    if sh_degree is None and not torch.isfinite(colors).all():
        raise NonFiniteInputError(non_finite_message("colors", colors), ("colors",))
    splats = project_and_shade_cpu(
        means, quats, scales, opacities, colors if sh_degree is not None else None, viewmats, Ks, width, height,
        sh_degree=sh_degree, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
        antialiased=(rasterize_mode == "antialiased"),
    )
    if sh_degree is None:
        splats = splats._replace(colors=_per_camera(colors, viewmats.shape[0]))
    return splats


def _project_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, near_plane,
                   far_plane, eps2d, radius_clip, rasterize_mode) -> ProjectedSplats:
    """The torch reference projection (:func:`fully_fused_projection`) and SH colours (:func:`sh_to_rgb`)."""
    n_cameras = viewmats.shape[0]
    proj = fully_fused_projection(
        means, quats, scales, viewmats, Ks, width, height,
        opacities=opacities, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
        calc_compensations=(rasterize_mode == "antialiased"),
    )
    opacities_c = opacities[None, :].expand(n_cameras, -1)
    if proj.compensations is not None:
        opacities_c = opacities_c * proj.compensations
    if sh_degree is None:
        colors_c = _per_camera(colors, n_cameras)
    else:
        visible = (proj.radii > 0).all(dim=-1)  # [C, N]
        camtoworlds = torch.linalg.inv(viewmats)
        dirs = means[None, :, :] - camtoworlds[:, None, :3, 3]  # [C, N, 3]
        shs = colors if colors.dim() == 4 else colors[None].expand(n_cameras, -1, -1, -1)
        colors_c = sh_to_rgb(sh_degree, dirs, shs, masks=visible)
    return ProjectedSplats(proj.radii, proj.means2d, proj.depths, proj.conics, opacities_c, colors_c)


def _per_camera(colors: Tensor, n_cameras: int) -> Tensor:
    """Post-activation colours [N, D] or [C, N, D] as [C, N, D]."""
    return colors if colors.dim() == 3 else colors[None].expand(n_cameras, -1, -1)


def _composite(
    splats: ProjectedSplats,
    width: int,
    height: int,
    backgrounds: Optional[Tensor],
    render_mode: str,
    absgrad: bool,
    tile_size: int,
    bin_tiles: Callable,
    rasterize: Callable,
    rasterizer: str,
) -> tuple[Tensor, Tensor, dict]:
    """Shared tail of the cpu and torch rasterizers: depth channels of the render mode, tile binning (``bin_tiles``),
    compositing (``rasterize``, a ``rasterize_to_pixels`` implementation), expected depth, and gsplat's meta."""
    radii, means2d, depths, conics, opacities_c, colors_c = splats
    assert colors_c is not None  # both projections fill the per-pair colours
    n_cameras = means2d.shape[0]
    if means2d.requires_grad:
        means2d.retain_grad()  # density control reads meta["means2d"].grad
    if render_mode in ("RGB+D", "RGB+ED"):
        colors_c = torch.cat([colors_c, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cameras, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        colors_c = depths[..., None]
        if backgrounds is not None:
            backgrounds = backgrounds.new_zeros(n_cameras, 1)
    if backgrounds is not None and backgrounds.shape[-1] != colors_c.shape[-1]:
        raise ValueError(
            f"backgrounds have {backgrounds.shape[-1]} channels but colors have {colors_c.shape[-1]} (render_mode {render_mode})"
        )

    tile_width, tile_height = tile_grid(width, height, tile_size)
    tiles_per_gauss, isect_ids, flatten_ids, isect_offsets = bin_tiles(means2d, radii, depths, tile_width,
                                                                       tile_height)
    render_colors, render_alphas = rasterize(
        means2d, conics, colors_c, opacities_c, width, height, tile_size, isect_offsets, flatten_ids,
        backgrounds=backgrounds, absgrad=absgrad and means2d.requires_grad,
    )
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=EXPECTED_DEPTH_ALPHA_MIN)],
            dim=-1,
        )
    meta = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": opacities_c,
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tiles_per_gauss": tiles_per_gauss,
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids,
        "isect_offsets": isect_offsets,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_batches": 1,
        "n_cameras": n_cameras,
        "rasterizer": rasterizer,
    }
    return render_colors, render_alphas, meta
