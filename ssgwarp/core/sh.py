"""Real spherical harmonics colour (degrees 0..3), the 3DGS basis.

``spherical_harmonics(degree, dirs, coeffs)`` matches gsplat's function of the
same name: directions are normalised inside, ``coeffs [..., K, 3]`` with
``K >= (degree+1)^2``, result ``[..., 3]`` (the caller adds 0.5 and clamps).
"""
from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """``[..., (degree+1)^2]`` basis values at unit directions ``dirs [..., 3]``."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def spherical_harmonics(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """SH colour ``[..., 3]`` of ``coeffs [..., K, 3]`` seen along ``dirs [..., 3]`` (any length)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be 0..3, got {degree}")
    k = (degree + 1) ** 2
    if coeffs.shape[-2] < k:
        raise ValueError(f"coeffs has {coeffs.shape[-2]} SH bases, degree {degree} needs {k}")
    d = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True).clamp_min(1e-30)
    basis = sh_basis(degree, d)
    return (basis[..., None] * coeffs[..., :k, :]).sum(dim=-2)
