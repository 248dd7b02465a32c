"""Stage 2 that can add detail: Gaussians split where the style loss wants finer colour than a splat can hold.

Stage 2 optimises colours only, so a reconstructed splat covering many pixels can take one colour, and
nothing finer than the reconstruction's splats appears (a brush stroke across a large smooth surface
cannot be painted). Before the optimisation, :func:`densify_for_style` splits the Gaussians whose
pixels *disagree* about the colour they want (G-Style, Kovacs et al. 2024, densify during stylization;
here the criterion is the style loss's own gradient):

For a view with image gradient ``g_p = dL/dI_p`` and each Gaussian's blending weights ``w_p`` over its
pixels, the colour gradient is ``sum_p w_p g_p``: the pixels' wishes averaged. What one colour cannot
give is their spread, ``D = sum_p w_p |g_p|^2 - |sum_p w_p g_p|^2 / sum_p w_p`` (the weighted variance of
the wishes times the weight): zero when every pixel wants the same change, large on a big splat under a
stroke edge. ``D`` comes from three backward passes through the rasterizer alone (image-space
``g``, ``g^2`` and ones pushed into ``sh_dc``), summed over a few evenly spaced training views.

The Gaussians with the largest ``D`` are split in two along their longest axis, moment-preserving: the
children sit at ``+-0.6 s`` with that axis' standard deviation ``0.8 s`` (mean and covariance of the pair
equal the parent's) and opacity ``1 - sqrt(1 - a)`` (two overlapping children block light as the parent
did at its centre), colours and identities copied; geometry then stays frozen and the content term
holds the look, while each child's colour is free. Up to ``budget x N`` new Gaussians, in ``rounds``
rounds (a child may split again). Splitting is deterministic for a scene, a loss and views; the parent
index is returned so a run can record it and resume on exactly the same Gaussians.
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch

from ..core.cameras import Cameras
from ..core.geometry import quat_to_rotmat
from ..errors import InputError
from ..raster.scene import GaussianScene

OFFSET = 0.6                       # children at +- OFFSET * s along the longest axis ...
SHRINK = math.sqrt(1 - OFFSET ** 2)  # ... with that axis' std SHRINK * s (0.8): the pair's variance is s^2


def split_gaussians(scene: GaussianScene, idx: torch.Tensor) -> tuple[GaussianScene, torch.Tensor]:
    """``scene`` with the Gaussians ``idx`` each replaced by two children (see module docs); returns the new
    scene and the parent index ``[N']`` (child -> original Gaussian) — the kept Gaussians first, in order,
    then the children in pairs."""
    idx = torch.unique(idx.long().to(scene.device))
    n = len(scene)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n):
        raise InputError(f"split_gaussians: indices out of range 0..{n - 1}")
    keep = torch.ones(n, dtype=torch.bool, device=scene.device)
    keep[idx] = False
    kept = torch.nonzero(keep)[:, 0]
    parent = torch.cat([kept, idx.repeat_interleave(2)])
    out = scene.subset(parent)
    if idx.numel() == 0:
        return out, parent
    m = len(kept)
    log_s = scene.log_scales[idx]
    axis = log_s.argmax(1)                                              # [k] the longest axis
    R = quat_to_rotmat(scene.quats[idx])                                # [k, 3, 3], columns: the local axes
    direction = R[torch.arange(len(idx), device=R.device), :, axis]     # [k, 3] world direction of that axis
    s = log_s.gather(1, axis[:, None]).exp()                            # [k, 1]
    offset = direction * s * OFFSET
    sign = torch.tensor([1.0, -1.0], device=scene.device, dtype=scene.dtype).repeat(len(idx))[:, None]
    means = out.means.clone()
    means[m:] = scene.means[idx].repeat_interleave(2, 0) + sign * offset.repeat_interleave(2, 0)
    log_scales = out.log_scales.clone()
    shrunk = log_s.clone()
    shrunk.scatter_(1, axis[:, None], (s * SHRINK).log())
    log_scales[m:] = shrunk.repeat_interleave(2, 0)
    a = torch.sigmoid(scene.logit_opacities[idx]).clamp(1e-6, 1 - 1e-6)
    a_child = (1 - torch.sqrt(1 - a)).clamp(1e-6, 1 - 1e-6)
    logits = out.logit_opacities.clone()
    logits[m:] = torch.logit(a_child).repeat_interleave(2)
    return out.replace(means=means, log_scales=log_scales, logit_opacities=logits), parent


def detail_demand(scene: GaussianScene, cameras: Cameras, views: list[int],
                  image_grad: Callable[[GaussianScene, int], torch.Tensor],
                  render: Callable[[GaussianScene, Cameras], torch.Tensor]) -> torch.Tensor:
    """``[N]`` per Gaussian, summed over the ``views`` of ``cameras``: ``D = sum w |g|^2 - |sum w g|^2 / sum w``
    (module docs). ``image_grad(scene, view) -> dL/dimage [H, W, 3]`` (the style loss's image gradient of
    that view's render); ``render(scene, camera) -> [1, H, W, 3]`` differentiable in ``scene.sh_dc``."""
    demand = torch.zeros(len(scene), dtype=torch.float64, device=scene.device)
    for v in views:
        cam = cameras[[v]]
        g = image_grad(scene, v).detach()[..., :3]
        sums = []
        for seed in (g, g * g, torch.ones_like(g[..., :1]).expand_as(g)):
            dc = scene.sh_dc.detach().clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(render(scene.replace(sh_dc=dc), cam)[0], dc, grad_outputs=seed)
            sums.append(grad.double())
        s1, s2, w = sums
        weight = w[:, 0].clamp_min(1e-12)
        demand += ((s2.sum(1) - (s1 ** 2).sum(1) / weight).clamp_min(0) * (w[:, 0] > 1e-12))
    return demand


def densify_for_style(scene: GaussianScene, cameras: Cameras,
                      image_grad: Callable[[GaussianScene, int], torch.Tensor],
                      render: Callable[[GaussianScene, Cameras], torch.Tensor], budget: float,
                      views: int = 8, rounds: int = 2, progress: Optional[Callable[[str], None]] = None
                      ) -> tuple[GaussianScene, torch.Tensor, dict]:
    """Split the Gaussians whose pixels disagree most about their colour (module docs).

    ``budget``: at most ``budget x N`` new Gaussians in all (0: nothing done), shared evenly over ``rounds``;
    ``views``: evenly spaced ``cameras`` scored per round; ``image_grad`` / ``render`` as
    :func:`detail_demand` (each round scores the scene as split so far). Only Gaussians with a positive
    demand are split. Returns ``(scene, parent [N'], record)``; ``record["indices"]``: the Gaussians split in
    each round, for :func:`replay`."""
    if not (budget >= 0 and math.isfinite(budget)):
        raise InputError(f"densify budget {budget}: must be a finite number >= 0")
    if views < 1 or rounds < 1:
        raise InputError(f"densify: views and rounds must be >= 1 (got {views}, {rounds})")
    n0 = len(scene)
    parent = torch.arange(n0, device=scene.device)
    total = int(budget * n0)
    record = {"budget": budget, "gaussians_before": n0, "split": [], "views": 0, "indices": []}
    if total == 0 or len(cameras) == 0:
        record["gaussians_after"] = n0
        return scene, parent, record
    pick = sorted({round(i * (len(cameras) - 1) / max(1, views - 1)) for i in range(min(views, len(cameras)))})
    record["views"] = len(pick)
    left = total
    for r in range(rounds):
        k = min(left, math.ceil(total / rounds))
        if k <= 0:
            break
        demand = detail_demand(scene, cameras, pick, image_grad, render)
        positive = int((demand > 0).sum())
        k = min(k, positive, len(scene))
        if k == 0:
            break
        top = torch.topk(demand, k, sorted=False).indices
        scene, p = split_gaussians(scene, top)
        parent = parent[p]
        record["split"].append(k)
        record["indices"].append(top.sort().values.cpu())
        left -= k
        if progress is not None:
            progress(f"densify round {r + 1}: split {k} Gaussians -> {len(scene)}")
    record["gaussians_after"] = len(scene)
    return scene, parent, record


def replay(scene: GaussianScene, indices: list[torch.Tensor]) -> tuple[GaussianScene, torch.Tensor]:
    """The splits of a :func:`densify_for_style` record (``record["indices"]``) applied again to ``scene``:
    the same Gaussians (how a resumed run gets exactly the scene it was optimising). Returns ``(scene,
    parent)``."""
    parent = torch.arange(len(scene), device=scene.device)
    for idx in indices:
        scene, p = split_gaussians(scene, idx)
        parent = parent[p]
    return scene, parent
