"""Spherical harmonics and camera centres over the Warp kernels of ``kernels/sh.py``, outside the
rasterizer's fused colour step (:class:`ssgwarp.raster.ops._Project` evaluates SH itself).

:func:`spherical_harmonics_warp` is the differentiable Warp version of
:func:`ssgwarp.core.sh.spherical_harmonics` (the spec); :func:`camera_centres` gives the
rasterizer the camera centres its SH directions start from when the view matrices need no gradient.
"""
from __future__ import annotations

import torch

from . import launch as L
from ..kernels import sh
from .launch import arr

Tensor = torch.Tensor


def camera_centres(viewmats: Tensor) -> Tensor:
    """Camera centres ``[C, 3]`` (the inverses' translations) of world-to-camera matrices ``[C, 4, 4]``
    in one kernel, no gradient (torch's batched inverse costs ~0.4 ms of host time per call on CUDA)."""
    vm = L.dense(viewmats.detach())
    out = torch.empty(vm.shape[0], 3, dtype=vm.dtype, device=vm.device)
    L.launch(sh.centres_kernel(L.scalar_of(vm.dtype)), vm.shape[0], [*arr(vm, 16), *arr(out, 3)], L.target(vm))
    return out


class _SH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, dirs, coeffs):
        shape = dirs.shape[:-1]
        d = L.dense(dirs).reshape(-1, 3)
        c = L.dense(coeffs).reshape(d.shape[0], -1, 3)
        M = c.shape[0]
        s = L.scalar_of(dirs.dtype)
        out = torch.empty_like(d)
        L.launch(sh.sh_kernel(s, degree), (1, M), [*L.grid(d, 1, M, 3, True), *_coeff_rows(c), *arr(out, 3)], L.target(d))
        ctx.save_for_backward(d, c, out)
        ctx.degree, ctx.shape, ctx.cshape = degree, shape, coeffs.shape
        return out.reshape(*shape, 3)

    @staticmethod
    def backward(ctx, g):
        d, c, out = ctx.saved_tensors
        s = L.scalar_of(d.dtype)
        M = d.shape[0]
        vd, vc = torch.zeros_like(d), torch.zeros_like(c)
        ga, g = L.grad_rows(g, 3, M)
        L.launch(sh.sh_kernel(s, ctx.degree), (1, M), [*L.grid(d, 1, M, 3, True), *_coeff_rows(c), *arr(out, 3)],
                 L.target(d), adj=[*L.grid(vd, 1, M, 3, True), *_coeff_rows(vc), *ga])
        return None, vd.reshape(*ctx.shape, 3), vc.reshape(ctx.cshape)


def _coeff_rows(c):
    return L.grid3(c, 1, c.shape[0], c.shape[1], 3, False)


def spherical_harmonics_warp(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Warp version of :func:`ssgwarp.core.sh.spherical_harmonics`: ``dirs [...,3]``, ``coeffs [...,K,3]`` → ``[...,3]``."""
    return _SH.apply(int(degree), dirs, coeffs)
