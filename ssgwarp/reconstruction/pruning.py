"""Contribution-based pruning: Gaussians that add little to any training view are removed, and a budget.

A Gaussian's contribution to a view is its blending weight summed over the view's pixels,
``sum_pixels alpha_i T_i`` (``T_i``: the transmittance in front of it): the number of pixels' worth of
colour it gives that view. Summed over the training views and divided by their number it is the mean
footprint the image loss sees; Gaussians whose footprint is below ``prune_contribution`` pixels
are removed (``DefaultStrategy.prune_contribution``; the scores Taming 3DGS and Speedy-Splat prune by are of this kind: accumulated blending
weights over the training views). ``prune_budget``: at most that many Gaussians are kept, those
with the largest contributions.

The contribution is the gradient of a one-channel render of ones with respect to those ones (the
image is ``sum_i c_i alpha_i T_i``; :func:`ssgwarp.raster.rendering.gaussian_sums`), so it comes from the
rasterizer's existing forward and backward, in chunks of views, with no extra kernel and no per-Gaussian statistic kept during training. Measured
deterministically (the same decision in every process of a multi-GPU run).

When (:func:`prune_steps`): halfway between opacity resets (the opacities have recovered from the
last reset; right after one every contribution is small), and once when densification stops: the rest
of the run, usually half of it, trains the smaller scene. Only with the default strategy (MCMC keeps a
fixed budget and relocates what it would prune).
"""
from __future__ import annotations

import torch

from ..errors import InputError
from ..raster.rendering import gaussian_sums
from ..raster.scene import GaussianScene

CHUNK = 8   # views per render when measuring


def contributions(params: dict, cameras, chunk: int = CHUNK) -> torch.Tensor:
    """``[N]``: each Gaussian's blending weight summed over the pixels of ``cameras`` (all of them), from the
    scene's stored parameters (``means``, ``quats``, ``log_scales``, ``logit_opacities``; no colour is
    rendered), ``chunk`` views per render (:func:`ssgwarp.raster.rendering.gaussian_sums` of a channel of ones)."""
    means = params["means"]
    scene = GaussianScene(means, params["log_scales"], params["quats"], params["logit_opacities"],
                          torch.zeros_like(means), None, None, 0)
    ones = torch.ones(cameras.height, cameras.width, 1, device=scene.device, dtype=scene.dtype)
    total = torch.zeros(len(scene), device=scene.device, dtype=scene.dtype)
    for i in range(0, len(cameras), chunk):
        cams = cameras[list(range(i, min(i + chunk, len(cameras))))]
        total += gaussian_sums(scene, cams, ones, deterministic=True, validate=False)[:, 0]
    return total


def prune_steps(strategy) -> set[int]:
    """The steps after which contribution pruning runs (a resolved default strategy): halfway between opacity resets
    before ``refine_stop`` (or, without resets, halfway through densification), and ``refine_stop``."""
    start, stop, reset = strategy.refine_start, strategy.refine_stop, strategy.reset_every or 0
    if stop <= start:
        return set()
    if reset > 0:
        out = {k * reset + reset // 2 for k in range(stop // reset + 1) if start < k * reset + reset // 2 < stop}
    else:
        out = {(start + stop) // 2}
    return out | {stop}


class ContributionPruning:
    """The trainer's hook: :meth:`step` after each optimisation step prunes at :func:`prune_steps`."""

    def __init__(self, strategy):
        if not hasattr(strategy, "prune_contribution"):
            raise InputError(f"contribution pruning (prune_contribution / prune_budget) is a knob of the default "
                             f"strategy, not of {strategy.name!r}")
        if strategy.prune_contribution < 0 or strategy.prune_budget < 0:
            raise InputError("DefaultStrategy.prune_contribution and .prune_budget must be >= 0")
        self.threshold = float(strategy.prune_contribution)
        self.budget = int(strategy.prune_budget or 0)
        self.steps = prune_steps(strategy)

    @classmethod
    def of(cls, strategy):
        """The hook a resolved strategy asks for, or None (pruning off: ``prune_contribution`` 0 and no budget,
        or a strategy without these knobs: MCMC keeps a fixed budget and relocates what it would prune)."""
        if not getattr(strategy, "prune_contribution", 0) and not getattr(strategy, "prune_budget", 0):
            return None
        return cls(strategy)

    def keep_mask(self, score: torch.Tensor) -> torch.Tensor:
        """Which Gaussians stay, from their mean contribution per view (pixels)."""
        keep = score >= self.threshold
        if self.budget and int(keep.sum()) > self.budget:
            top = torch.topk(torch.where(keep, score, torch.full_like(score, -1.0)), self.budget).indices
            keep = torch.zeros_like(keep)
            keep[top] = True
        return keep

    def step(self, gaussians, step: int, views) -> dict:
        """Prune ``gaussians`` (a :class:`~ssgwarp.reconstruction.gaussians.GaussianParams`) when ``step`` is one of
        :attr:`steps`, scoring them on the cameras ``views()`` gives (the training views). Returns what it did."""
        if step not in self.steps or len(gaussians) == 0:
            return {}
        cameras = views()
        score = contributions(gaussians.params, cameras) / max(1, len(cameras))
        keep = self.keep_mask(score)
        n = int((~keep).sum())
        if 0 < n < len(gaussians):
            gaussians.keep(keep)
        else:
            n = 0
        return {"contribution_prune": n}
