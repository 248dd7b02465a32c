"""The scene model: a set of 3D Gaussians holding only what the scene uses.

Parameters are stored unconstrained (log-scales, logit-opacities, raw
quaternions) as in the INRIA 3DGS layout. A scene at SH degree 0 has no
higher-band tensor (``sh_rest is None``) and a scene that was never grouped has
no identity tensor (``identities is None``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.geometry import knn_mean_distance
from .rendering import render

SH_C0 = 0.28209479177387814


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """SH DC coefficient whose degree-0 colour (``C0 * dc + 0.5``) is ``rgb``."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * SH_C0 + 0.5


@dataclass
class GaussianScene:
    """N Gaussians.

    Attributes:
        means: ``[N, 3]`` world positions.
        log_scales: ``[N, 3]`` natural log of the per-axis standard deviations.
        quats: ``[N, 4]`` rotations, wxyz, not necessarily normalised.
        logit_opacities: ``[N]``.
        sh_dc: ``[N, 3]`` degree-0 SH coefficients.
        sh_rest: ``[N, (d+1)^2 - 1, 3]`` higher bands, or None at degree 0.
        identities: ``[N, E]`` Gaussian Grouping identity encodings, or None.
        sh_degree: the degree ``d`` the scene carries.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    logit_opacities: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: Optional[torch.Tensor] = None
    identities: Optional[torch.Tensor] = None
    sh_degree: int = 0

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {
            "means": (n, 3), "log_scales": (n, 3), "quats": (n, 4),
            "logit_opacities": (n,), "sh_dc": (n, 3),
        }
        for name, shape in shapes.items():
            t = getattr(self, name)
            if tuple(t.shape) != shape:
                raise InputError(f"GaussianScene.{name}: expected shape {shape}, got {tuple(t.shape)}")
        if not 0 <= self.sh_degree <= 3:
            raise InputError(f"GaussianScene: sh_degree must be 0..3, got {self.sh_degree}")
        k = (self.sh_degree + 1) ** 2 - 1
        if self.sh_degree == 0:
            if self.sh_rest is not None and self.sh_rest.numel() > 0:
                raise InputError("GaussianScene: sh_rest given at sh_degree 0 (a degree-0 scene holds no higher bands)")
            self.sh_rest = None
        elif self.sh_rest is None or tuple(self.sh_rest.shape) != (n, k, 3):
            got = None if self.sh_rest is None else tuple(self.sh_rest.shape)
            raise InputError(f"GaussianScene.sh_rest: expected {(n, k, 3)} at degree {self.sh_degree}, got {got}")
        if self.identities is not None and (self.identities.ndim != 2 or self.identities.shape[0] != n):
            raise InputError(f"GaussianScene.identities: expected [N={n}, E], got {tuple(self.identities.shape)}")

    # -- derived -------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.logit_opacities)

    @property
    def sh_coeffs(self) -> torch.Tensor:
        """``[N, (d+1)^2, 3]`` all SH coefficients (DC first)."""
        if self.sh_rest is None:
            return self.sh_dc[:, None, :]
        return torch.cat([self.sh_dc[:, None, :], self.sh_rest], dim=1)

    @property
    def base_colors(self) -> torch.Tensor:
        """``[N, 3]`` the view-independent (degree-0) colour."""
        return sh_dc_to_rgb(self.sh_dc).clamp_min(0.0)

    def tensors(self) -> dict[str, torch.Tensor]:
        """The tensors the scene holds, by field name (absent ones left out)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                out[f.name] = v
        return out

    def replace(self, **kw) -> "GaussianScene":
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(kw)
        return GaussianScene(**d)

    def map(self, fn) -> "GaussianScene":
        """A new scene with ``fn`` applied to every tensor."""
        return self.replace(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "GaussianScene":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "GaussianScene":
        return self.map(lambda t: t.detach().clone())

    def subset(self, idx: torch.Tensor) -> "GaussianScene":
        """The Gaussians at ``idx`` (bool mask or indices)."""
        return self.map(lambda t: t[idx])

    def with_sh_degree(self, degree: int) -> "GaussianScene":
        """The same scene carrying SH up to ``degree`` (new bands start at 0, dropped bands are removed)."""
        n = len(self)
        if degree == 0:
            return self.replace(sh_rest=None, sh_degree=0)
        k = (degree + 1) ** 2 - 1
        rest = torch.zeros(n, k, 3, dtype=self.dtype, device=self.device)
        if self.sh_rest is not None:
            m = min(k, self.sh_rest.shape[1])
            rest[:, :m] = self.sh_rest[:, :m]
        return self.replace(sh_rest=rest, sh_degree=degree)

    @classmethod
    def from_points(cls, xyz: torch.Tensor, rgb: torch.Tensor, *, sh_degree: int = 0,
                    opacity: float = 0.1, scale: Optional[torch.Tensor] = None) -> "GaussianScene":
        """Isotropic Gaussians at ``xyz [N,3]`` with colours ``rgb [N,3]`` in [0,1].

        ``scale`` (``[N]``) defaults to the mean distance to the 3 nearest neighbours.
        """
        xyz = torch.as_tensor(xyz)
        rgb = torch.as_tensor(rgb, dtype=xyz.dtype, device=xyz.device)
        n = xyz.shape[0]
        if scale is None:
            scale = knn_mean_distance(xyz, k=3).clamp_min(1e-7)
        log_s = torch.log(scale)[:, None].repeat(1, 3)
        quats = torch.zeros(n, 4, dtype=xyz.dtype, device=xyz.device)
        quats[:, 0] = 1.0
        logit = torch.full((n,), float(torch.logit(torch.tensor(opacity))), dtype=xyz.dtype, device=xyz.device)
        scene = cls(xyz.clone(), log_s, quats, logit, rgb_to_sh_dc(rgb), None, None, 0)
        return scene.with_sh_degree(sh_degree) if sh_degree > 0 else scene

    # -- rendering -------------------------------------------------------------
    def render(self, cameras: Cameras, *, sh_degree: Optional[int] = None, identities: bool = False,
               extra: Optional[torch.Tensor] = None, rgb: bool = True, **kwargs):
        """Render the scene from ``cameras`` (:func:`ssgwarp.raster.rendering.render`).

        Channels, in order: RGB (SH evaluated up to ``sh_degree``, default the
        scene's degree) if ``rgb``; then the identity encodings if
        ``identities``; then ``extra [N, X]`` if given. All go through one
        blending pass. ``kwargs`` are passed on (``render_mode``,
        ``backgrounds``, knobs...). Returns ``(colors [C,H,W,D], alphas [C,H,W,1], meta)``.
        """
        return render(self, cameras, sh_degree=sh_degree, rgb=rgb, identities=identities, extra=extra, **kwargs)
