"""Frames: similarity transforms between them, fitted or applied, and what they do to SH colour.

* :class:`Similarity` (``x -> s R x + t``, ``R`` a proper rotation): composed (``@``), inverted,
  applied to points and to :class:`~ssgwarp.core.cameras.Cameras`;
* :func:`umeyama` fits one to matched points (Umeyama 1991);
* :func:`sh_rotation` gives per SH band the matrix taking the coefficients of ``f`` to those of
  ``f(R^T d)``, solved from the basis at a fixed set of directions (exact, since each band is a
  rotation-invariant space); :func:`rotate_sh` applies it; :func:`quat_mul` composes rotations.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError
from .cameras import Cameras
from .sh import sh_basis


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * R @ x + t`` (``R`` a proper rotation, float64 numpy)."""

    scale: float = 1.0
    R: np.ndarray = None  # type: ignore[assignment]
    t: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        R = np.eye(3) if self.R is None else np.asarray(self.R, dtype=np.float64).reshape(3, 3)
        t = np.zeros(3) if self.t is None else np.asarray(self.t, dtype=np.float64).reshape(3)
        if not (np.isfinite(R).all() and np.isfinite(t).all() and math.isfinite(self.scale) and self.scale > 0):
            raise InputError(f"similarity transform: non-finite values or scale {self.scale} <= 0")
        if abs(np.linalg.det(R) - 1.0) > 1e-4 or np.abs(R @ R.T - np.eye(3)).max() > 1e-4:
            raise InputError("similarity transform: the rotation part is not a proper rotation (a mirror or "
                             "a shear cannot be applied to Gaussians' SH and rotations)")
        U, _, Vt = np.linalg.svd(R)       # the nearest exact rotation (files store float32 matrices)
        object.__setattr__(self, "R", U @ Vt)
        object.__setattr__(self, "t", t)

    @classmethod
    def from_matrix(cls, m) -> "Similarity":
        """From a 3x4 / 4x4 matrix ``[s R | t]`` (``s``: the cube root of its 3x3 part's determinant)."""
        m = np.asarray(m, dtype=np.float64)
        if m.shape not in ((3, 4), (4, 4)):
            raise InputError(f"similarity transform: expected a 3x4 or 4x4 matrix, got shape {m.shape}")
        A = m[:3, :3]
        s = float(np.cbrt(np.linalg.det(A)))
        if not s > 0:
            raise InputError("similarity transform: the matrix mirrors or collapses space (det <= 0)")
        return cls(s, A / s, m[:3, 3])

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m

    @property
    def is_identity(self) -> bool:
        return bool(np.allclose(self.matrix, np.eye(4), atol=1e-12))

    def inverse(self) -> "Similarity":
        return Similarity(1.0 / self.scale, self.R.T, -(self.R.T @ self.t) / self.scale)

    def __matmul__(self, other: "Similarity") -> "Similarity":
        """``(self @ other)(x) = self(other(x))``."""
        return Similarity(self.scale * other.scale, self.R @ other.R, self.scale * self.R @ other.t + self.t)

    def points(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, dtype=np.float64) @ self.R.T + self.t

    def cameras(self, cams: Cameras) -> Cameras:
        """The same cameras in the new frame (world-to-camera ``[R_c | t_c]`` becomes
        ``[R_c R^T | s t_c - R_c R^T t]``: a camera sees the moved scene as before, depths times ``s``)."""
        vm = cams.viewmats.double().cpu().numpy().copy()
        Rc, tc = vm[:, :3, :3], vm[:, :3, 3]
        new = vm.copy()
        new[:, :3, :3] = Rc @ self.R.T
        new[:, :3, 3] = self.scale * tc - np.einsum("cij,j->ci", new[:, :3, :3], self.t)
        return Cameras(torch.from_numpy(new).to(cams.viewmats.dtype), cams.Ks.clone(), cams.width, cams.height,
                       list(cams.names))

    def record(self) -> dict:
        return {"scale": self.scale, "rotation": self.R.tolist(), "translation": self.t.tolist()}


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions (``a * b``: rotate by ``b``, then by ``a``)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


# a fixed, well-spread set of unit directions (a Fibonacci sphere) for the SH band matrices
def _directions(n: int = 64) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1)


def sh_rotation(R, degree: int) -> list[torch.Tensor]:
    """Per band ``l = 1..degree`` the ``[2l+1, 2l+1]`` float64 matrix ``B_l`` with ``Y_l(d) . (B_l c) =
    Y_l(R^T d) . c`` for every direction ``d``: the coefficients ``B_l c`` give, along ``R d``, the
    colour ``c`` gave along ``d`` (the basis of :func:`ssgwarp.raster.sh.sh_basis`)."""
    Rm = torch.as_tensor(np.asarray(R, dtype=np.float64))
    d = _directions()
    Y, Yr = sh_basis(degree, d), sh_basis(degree, d @ Rm)   # (row d @ R is (R^T d) as a row)
    out = []
    for l in range(1, degree + 1):
        sl = slice(l * l, (l + 1) * (l + 1))
        out.append(torch.linalg.lstsq(Y[:, sl], Yr[:, sl]).solution)
    return out


def rotate_sh(sh_rest: torch.Tensor, R, degree: int) -> torch.Tensor:
    """``sh_rest [N, (degree+1)^2 - 1, 3]`` of Gaussians whose scene is rotated by ``R``."""
    out = torch.empty_like(sh_rest)
    for l, B in enumerate(sh_rotation(R, degree), start=1):
        a, b = l * l - 1, (l + 1) * (l + 1) - 1
        out[:, a:b] = torch.einsum("ij,njc->nic", B.to(sh_rest), sh_rest[:, a:b])
    return out


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity minimising ``sum |dst_i - (s R src_i + t)|^2`` (Umeyama 1991); needs 3 or more
    points not on a line."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var = (xs ** 2).sum() / len(src)
    if len(src) < 3 or var <= 0:
        raise InputError("alignment needs at least 3 distinct camera positions")
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / var)
    return Similarity(s, R, mu_d - s * R @ mu_s)
