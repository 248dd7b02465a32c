"""Far-field densification: the gradient statistic of far Gaussians, scaled by their footprint on screen.

3DGS densifies a Gaussian when the mean norm of its view-space positional gradient reaches a threshold. A far
Gaussian of a backdrop (:mod:`ssgwarp.reconstruction.backdrop`) starts as wide as the gaps of a sparse far cloud:
tens to hundreds of pixels on screen over a textured facade. Each pixel pulls its mean a different way and the
pulls cancel, so its mean gradient stays below the threshold however much detail it blurs, and it is never split;
the budget goes to the near Gaussians instead (docs/reconstruction.md, "Far-field densification", measured on the
procedural inside-out capture with ``benchmarks/captures.py inside-out``). Absolute-gradient rules (AbsGS) address the
cancellation in the rasterizer's backward pass; this rule uses the footprint the forward pass already measures.

The rule (:class:`FarField`): for a far Gaussian, at least :data:`FAR_EXTENTS` extents (the extent: 1.1 x the
cameras' radius) from the cameras' centre, the statistic that is compared to ``grad_threshold`` (and that ranks
candidates when the budget is reached) is its mean gradient times ``max(1, r / SPLIT_RADIUS_PX)``,
``r = 3 x (largest scale) x focal / distance``: its screen radius in pixels (the rasterizer's 3-sigma radius; that
far out the distance from the cameras' centre stands for the depth in every view to within 1 / FAR_EXTENTS). A far
Gaussian wider than :data:`SPLIT_RADIUS_PX` pixels is split once its gradient reaches the threshold divided by how
many times wider it is; split down to that size, the 3DGS rule applies again. Nearer Gaussians, and any capture
without a far field (no backdrop and cameras that do not look outward), keep the 3DGS statistic:
:class:`~ssgwarp.reconstruction.strategy.DefaultStrategy` applies a :class:`FarField` only when the trainer gives
it a far field (the backdrop's decision: :meth:`~ssgwarp.reconstruction.strategy.Strategy.far_field`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

SPLIT_RADIUS_PX = 8.0   # far Gaussians wider than this (screen radius, pixels) get their gradient statistic scaled
                        # (a value for DefaultStrategy.far_split_px, the knob: its default 0 leaves the rule off)
FAR_EXTENTS = 5.0       # far: at least this many extents (1.1 x the cameras' radius) from the cameras' centre


@dataclass
class FarField:
    """The far-field rule for Gaussians at least ``min_distance`` from ``center`` (``[3]``), for images of focal
    length ``focal_px`` (pixels; see the module docs)."""

    center: torch.Tensor
    min_distance: float
    focal_px: float
    split_radius_px: float = SPLIT_RADIUS_PX

    @classmethod
    def around(cls, center: torch.Tensor, extent: float, focal_px: float,
               split_radius_px: float = SPLIT_RADIUS_PX) -> "FarField":
        """The rule for Gaussians :data:`FAR_EXTENTS` extents or more from the cameras' centre."""
        return cls(center, FAR_EXTENTS * float(extent), float(focal_px), float(split_radius_px))

    def distance(self, means: torch.Tensor) -> torch.Tensor:
        """``[N]`` each Gaussian's distance from the centre."""
        return (means - self.center.to(means.device, means.dtype)).norm(dim=1)

    def screen_radius(self, means: torch.Tensor, log_scales: torch.Tensor, distance=None) -> torch.Tensor:
        """``[N]`` each Gaussian's screen radius (pixels, 3 sigma of its largest axis) at its distance from the centre
        (``distance``: :meth:`distance`, when already computed)."""
        d = (self.distance(means) if distance is None else distance).clamp_min(1e-12)
        return 3.0 * torch.exp(log_scales).amax(dim=1) * self.focal_px / d

    @torch.no_grad()
    def statistic(self, avg: torch.Tensor, means: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
        """The densification statistic: ``avg`` (each Gaussian's mean gradient) times ``max(1, r / split_radius_px)``
        for the far Gaussians, ``avg`` for the others."""
        d = self.distance(means)
        boost = (self.screen_radius(means, log_scales, d) / self.split_radius_px).clamp_min(1.0).to(avg.dtype)
        return torch.where(d >= self.min_distance, avg * boost, avg)
