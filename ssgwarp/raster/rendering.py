"""Rendering a scene through cameras: the one home every stage renders through.

* :func:`gaussian_colors` -- the per-camera colour rows of a scene: RGB from its spherical
  harmonics (up to a degree), its identity encodings, extra channels, in that order;
* :func:`render` -- one :func:`ssgwarp.rasterization` call (any gsplat-compatible ``rasterize``)
  for all cameras, differentiable. When RGB is the only channel the rasterizer evaluates the
  SH itself (its fused SH kernel); otherwise the channels are built here and blended in one pass;
* :func:`render_views` -- no-gradient renders, one camera at a time (bounded memory), with the
  colour composited over a background: ``Views(rgb [V,H,W,3], depth [V,H,W], alpha [V,H,W])``;
* :func:`render_to_files` -- :func:`render_views` written as PNGs, one per camera;
* :func:`gaussian_sums` -- per-Gaussian sums of a per-pixel signal weighted by the blending weights (a channel
  of ones: each Gaussian's footprint in pixels), from one forward and one backward pass.

The scene is read by attribute (``means``, ``quats``, ``scales``, ``opacities``, ``sh_dc``,
``sh_rest`` (else ``sh_coeffs``), ``sh_degree``, ``identities``): this module does not import
:mod:`ssgwarp.raster.scene`, whose :meth:`~ssgwarp.raster.scene.GaussianScene.render` calls :func:`render`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple, Optional, Sequence

import torch

from ..errors import InputError
from ..core.fileio import write_image
from .rasterize import rasterization, rasterization_from_parameters
from ..core.sh import C0, spherical_harmonics


class Views(NamedTuple):
    """Renders of V cameras: ``rgb [V,H,W,3]`` in [0, 1], ``depth [V,H,W]`` (expected depth; None
    when not asked for), ``alpha [V,H,W]``."""

    rgb: torch.Tensor
    depth: Optional[torch.Tensor]
    alpha: torch.Tensor


def _degree(scene, sh_degree: Optional[int]) -> int:
    return scene.sh_degree if sh_degree is None else min(int(sh_degree), scene.sh_degree)


def gaussian_colors(scene, cameras, *, sh_degree: Optional[int] = None, rgb: bool = True,
                    identities: bool = False, extra: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[C, N, D]``: each camera's colour rows: RGB (SH up to ``sh_degree``, default the scene's,
    ``+ 0.5`` clamped at 0) if ``rgb``, then the identity encodings if ``identities``, then
    ``extra`` (``[N, X]`` shared by the cameras, or ``[C, N, X]``)."""
    C = len(cameras)
    parts = []
    if rgb:
        deg = _degree(scene, sh_degree)
        if deg == 0:
            parts.append((scene.sh_dc * C0 + 0.5).clamp_min(0.0)[None].expand(C, -1, -1))
        else:
            dirs = scene.means[None] - cameras.centers.to(scene.means)[:, None]
            coeffs = scene.sh_coeffs[:, : (deg + 1) ** 2]
            parts.append((spherical_harmonics(deg, dirs, coeffs[None].expand(C, -1, -1, -1)) + 0.5).clamp_min(0.0))
    if identities:
        if scene.identities is None:
            raise InputError("scene has no identity encodings: run `ssgwarp group` first")
        parts.append(scene.identities[None].expand(C, -1, -1))
    if extra is not None:
        parts.append(extra[None].expand(C, -1, -1) if extra.ndim == 2 else extra)
    if not parts:
        raise ValueError("render: nothing to render (rgb=False and no identities or extra)")
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)


def _coefficients(scene, degree: int) -> torch.Tensor:
    """``[N, (degree+1)^2, 3]``: the scene's SH coefficients up to ``degree`` (at most the scene's),
    contiguous: at degree 0 a view of the DC term (no copy; the higher bands then get no gradient),
    else the DC term and the bands needed, joined (not all of them, then cut and copied again)."""
    if not hasattr(scene, "sh_rest"):  # (a scene-like object without the two tensors)
        return scene.sh_coeffs[:, : (degree + 1) ** 2]
    rest = scene.sh_rest
    if degree == 0 or rest is None:
        return scene.sh_dc[:, None, :]
    return torch.cat([scene.sh_dc[:, None, :], rest[:, : (degree + 1) ** 2 - 1]], dim=1)


def render(scene, cameras, *, sh_degree: Optional[int] = None, rgb: bool = True, identities: bool = False,
           extra: Optional[torch.Tensor] = None, rasterize: Optional[Callable] = None, from_parameters: bool = False,
           **kwargs):
    """Render ``scene`` from ``cameras`` in one rasterizer call (differentiable).

    Channels as :func:`gaussian_colors`; ``kwargs`` go to the rasterizer (``render_mode``,
    ``backgrounds``, knobs...). ``from_parameters`` (ssgwarp's rasterizer, ``rasterize`` None): the
    scene's log-scales and logit opacities go to the kernels, which activate them
    (:func:`ssgwarp.raster.rasterize.rasterization_from_parameters`: the training loop's; the same
    images and gradients to float rounding). Returns ``(colors [C,H,W,D], alphas [C,H,W,1], meta)``."""
    viewmats = cameras.viewmats.to(scene.means)
    Ks = cameras.Ks.to(scene.means)
    if from_parameters and rasterize is None and hasattr(scene, "log_scales"):
        rasterize = rasterization_from_parameters
        scales, opacities = scene.log_scales, scene.logit_opacities
    else:
        rasterize = rasterization if rasterize is None else rasterize
        scales, opacities = scene.scales, scene.opacities
    if rgb and not identities and extra is None:   # SH in the rasterizer (fused kernel, gsplat's convention)
        deg = _degree(scene, sh_degree)
        return rasterize(scene.means, scene.quats, scales, opacities, _coefficients(scene, deg),
                         viewmats, Ks, cameras.width, cameras.height, sh_degree=deg, **kwargs)
    colors = gaussian_colors(scene, cameras, sh_degree=sh_degree, rgb=rgb, identities=identities, extra=extra)
    return rasterize(scene.means, scene.quats, scales, opacities, colors, viewmats, Ks,
                     cameras.width, cameras.height, **kwargs)


def gaussian_sums(scene, cameras, signal: torch.Tensor, **raster_kwargs) -> torch.Tensor:
    """``[N, D]``: for each Gaussian, ``sum_p w_i(p) signal[p]`` over the pixels of ``cameras`` (one view or
    several, summed), where ``w_i(p) = T_i(p) alpha_i(p)`` is its blending weight at pixel p.

    The rasterizer blends D channels of zeros; the gradient of ``sum_p signal[p] . image[p]`` with
    respect to those channel values is exactly these sums (one forward and one backward pass).
    ``signal [H, W, D]`` (every view) or ``[C, H, W, D]``; a channel of ones gives each Gaussian's total
    weight in the views (in pixels).
    """
    geom = scene.replace(identities=None).map(torch.Tensor.detach)
    x = torch.zeros(len(geom), signal.shape[-1], dtype=geom.dtype, device=geom.device, requires_grad=True)
    with torch.enable_grad():
        img, _, _ = geom.render(cameras.to(geom.device), rgb=False, extra=x, **raster_kwargs)
        # (the gradient of the sum of image x signal: exactly grad_outputs=signal, without the shape check that
        # imports torch.fx's symbolic shapes and sympy, ~0.3 s, the first time a gradient is handed in)
        (w,) = torch.autograd.grad((img * signal.to(img.device, img.dtype)).sum(), x)
    return w.detach()


def background_tensor(background, like: torch.Tensor) -> torch.Tensor:
    """``background`` (a name: white / black, or three numbers) as an RGB tensor like ``like``."""
    if isinstance(background, str):
        named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
        if background.lower() not in named:
            raise InputError(f"background '{background}': expected white, black or three numbers")
        background = named[background.lower()]
    return torch.as_tensor(background, dtype=like.dtype, device=like.device).reshape(-1)[:3]


@torch.no_grad()
def render_views(scene, cameras, background: Optional[Sequence[float]] = None, *, depth: bool = True,
                 sh_degree: Optional[int] = None, desc: Optional[str] = None, progress: bool = False,
                 **kwargs) -> Views:
    """Render ``cameras`` one at a time without gradients: colour composited over ``background``
    (None: over black, i.e. premultiplied) and clamped to [0, 1], expected depth (``depth``), alpha.
    A progress bar when ``progress`` or ``desc`` is given."""
    from ..core.progress import tqdm

    rgbs, depths, alphas = [], [], []
    bg = None if background is None else background_tensor(background, scene.means)
    for i in tqdm(range(len(cameras)), desc=desc, unit="view", disable=not (progress or desc), leave=False):
        cam = cameras[i].to(scene.device)
        colors, alpha, _ = render(scene, cam, sh_degree=sh_degree, render_mode="RGB+ED" if depth else "RGB",
                                  **kwargs)
        rgb, a = colors[0, ..., :3], alpha[0, ..., 0]
        if bg is not None:
            rgb = rgb + (1.0 - a)[..., None] * bg
        rgbs.append(rgb.clamp(0.0, 1.0))
        alphas.append(a)
        if depth:
            depths.append(colors[0, ..., 3])
    return Views(torch.stack(rgbs), torch.stack(depths) if depth else None, torch.stack(alphas))


def render_to_files(scene, cameras, out_dir: str | Path, *, background=(1.0, 1.0, 1.0),
                    names: Optional[list[str]] = None, progress: bool = True, environment=None) -> list[Path]:
    """Render ``scene`` from each camera to ``out_dir/<name>.png`` (names default to the cameras'
    image names). ``environment``: an :class:`ssgwarp.raster.environment.Environment` composited behind the
    splats instead of ``background`` (a run's sky). Returns the written paths."""
    from ..core.progress import tqdm

    out_dir = Path(out_dir)
    names = names or list(cameras.names)
    paths = []
    for i in tqdm(range(len(cameras)), desc="render", unit="view", disable=not progress):
        if environment is None:
            v = render_views(scene, cameras[i], background, depth=False)
            rgb = v.rgb[0]
        else:
            v = render_views(scene, cameras[i], None, depth=False)
            cam = cameras[i].to(environment.grid.device)
            rgb = environment.composite(v.rgb.to(environment.grid.device), v.alpha[..., None].to(environment.grid.device),
                                        cam)[0].clamp(0.0, 1.0)
        stem = Path(names[i]).with_suffix("").as_posix().replace("/", "_")
        paths.append(write_image(out_dir / f"{stem}.png", rgb))
    return paths
