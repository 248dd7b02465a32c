"""The blend-spread term of Stage 2: colours that differ along a ray are colours that differ between views.

A pixel's colour is the blend ``sum_i w_i c_i`` of the Gaussians its ray crosses, with weights
``w_i = alpha_i T_i`` that change with the viewpoint. When those Gaussians carry the same colour the
pixel is the same from every view; when Stage 2 paints texture by giving overlapping Gaussians
different colours (the front one red, the one behind it blue), one view sees red and the next one
purple: the stylized scene flickers even though every colour is view-independent. The spread of the
colours along a ray, weighted as the blend weighs them,

    spread = sum_i w_i c_i^2 - (sum_i w_i c_i)^2 / alpha        (alpha = sum_i w_i, per channel)

is ``alpha`` times the weighted variance of the colours the pixel mixes: 0 when they agree, whatever
their colour, so the term leaves the texture *between* surfaces free and penalises only texture that
exists in one view's blend. It is rendered in the same rasterizer pass as the image, as extra
channels (``c``, ``c^2`` and a constant 1, with no background: :func:`render_with_spread`), and
:func:`blend_spread` turns those channels into the mean spread over the pixels. :func:`empty_loss` is Stage 2's
other per-pixel term: empty pixels keep the unstylized render (``--hold-empty``).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..core.cameras import Cameras
from ..raster import rendering

SPREAD_CHANNELS = 10    # composited RGB (3), sum w c (3), sum w c^2 (3), alpha (1)


def render_with_spread(scene, cams: Cameras, background: Optional[torch.Tensor] = None, **kwargs) -> torch.Tensor:
    """``[C, H, W, 10]``: the RGB render composited over ``background`` (as Stage 2's plain render),
    then ``sum w c``, ``sum w c^2`` and ``alpha``, from one differentiable rasterizer call of 7
    channels (the colours as :func:`ssgwarp.raster.rendering.gaussian_colors` gives them)."""
    cams = cams.to(scene.device)
    colors = rendering.gaussian_colors(scene, cams)                              # [C, N, 3]
    rows = torch.cat([colors, colors * colors, torch.ones_like(colors[..., :1])], dim=-1)
    out, _, _ = rendering.render(scene, cams, rgb=False, extra=rows, **kwargs)   # no background
    rgb = out[..., :3]
    if background is not None:   # composited as the rasterizer composites: + (1 - alpha) background
        rgb = rgb + (1.0 - out[..., 6:7]) * background.to(out.device, out.dtype).reshape(1, 1, 1, 3)
    return torch.cat([rgb, out[..., :7]], dim=-1)


def blend_spread(channels: torch.Tensor, eps: float = 1e-4) -> torch.Tensor:
    """Mean over pixels of ``sum_ch (sum w c^2 - (sum w c)^2 / alpha)`` from the channels of
    :func:`render_with_spread` (``[..., 10]``); pixels with ``alpha < eps`` count as 0."""
    c, c2, alpha = channels[..., 3:6], channels[..., 6:9], channels[..., 9:10]
    spread = c2 - c * c / alpha.clamp_min(eps)
    spread = torch.where(alpha > eps, spread, torch.zeros_like(spread))
    return spread.sum(-1).mean()


def empty_loss(image: torch.Tensor, original: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Stage 2's empty-region term (``--hold-empty``): ``mean((1 - a) |I - I0|^2) / max(mean(1 - a), 0.01)`` for
    ``image``/``original [H, W, 3]`` and the original's accumulated opacity ``alpha [H, W]``: the pixels the
    unstylized scene leaves (nearly) empty keep its render, so low-opacity Gaussians over the background do not
    become coloured floaters; ~0 on a capture that fills the frame."""
    empty = 1 - alpha.to(image).clamp(0, 1)
    return (empty[..., None] * (image - original.to(image)) ** 2).mean() / empty.mean().clamp_min(0.01)
