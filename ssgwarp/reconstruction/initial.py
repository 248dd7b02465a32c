"""A reconstruction's initial scene: the capture's points (at most ``recipe.init_max_points``, and within the
budget of a budgeted strategy: a seeded subsample), far points behind them when the capture needs a backdrop
(:mod:`ssgwarp.reconstruction.backdrop`), one isotropic Gaussian per point sized by its 3 nearest neighbours
(``recipe.init_scale``), at ``recipe.init_opacity``, SH degree 0. :class:`~ssgwarp.reconstruction.trainer.Trainer`
starts from it unless given a scene.
"""
from __future__ import annotations

from typing import Optional

import torch

from ..core.geometry import knn_mean_distance
from ..errors import InputError
from ..raster.scene import GaussianScene
from .backdrop import with_backdrop
from .recipe import Recipe, initial_count
from .strategy import Strategy

__all__ = ["initial_scene"]


def initial_scene(data, recipe: Recipe, strategy: Strategy, *, backdrop_mode: str, seed: int,
                  device) -> tuple[GaussianScene, Optional[object]]:
    """``(scene, backdrop)``: the initial scene of ``data`` (see the module docs) and the backdrop decision
    (:func:`ssgwarp.reconstruction.backdrop.with_backdrop`'s)."""
    if data.points is None:
        raise InputError("the capture has no initial points (and none were generated); pass a scene")
    xyz, rgb = data.points
    xyz, rgb = xyz.float().cpu(), rgb.float().cpu()
    m = initial_count(len(xyz), recipe, strategy)
    if len(xyz) > m:
        g = torch.Generator().manual_seed(seed + 3)
        idx = torch.randperm(len(xyz), generator=g)[:m].sort().values
        xyz, rgb = xyz[idx], rgb[idx]
    if len(xyz) == 0:
        raise InputError("the capture has an empty point cloud")
    xyz, rgb, backdrop = with_backdrop(data, xyz, rgb, backdrop_mode,
                                      strategy.max_gaussians if strategy.budgeted else None, seed)
    xyz = xyz.to(device)
    scale = knn_mean_distance(xyz, k=3).clamp_min(1e-7) * recipe.init_scale
    return GaussianScene.from_points(xyz, rgb.to(device), sh_degree=0, opacity=recipe.init_opacity,
                                     scale=scale), backdrop
