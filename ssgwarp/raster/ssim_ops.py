"""The 3DGS photometric loss (L1 + D-SSIM) as one differentiable op over the Warp kernels of
``kernels/ssim.py``: two launches forward, two backward, images read in place over their strides.

:func:`photometric_warp` is the fused form of ``ssgwarp.services.losses.photometric`` (the spec,
in torch: about 20 kernels forward and as many backward); ``ssgwarp.services.losses`` chooses
between them.
"""
from __future__ import annotations

from functools import partial

import torch

from . import cpu_threads
from . import launch as L
from ..kernels import ssim as K

Tensor = torch.Tensor


def _image(t: Tensor) -> tuple:
    """4-D Warp array descriptor ``[V, H, W, C]`` over ``t``'s own strides (no copy)."""
    es = t.element_size()
    s = t.stride()
    return (t.data_ptr(), 0, *t.shape, s[0] * es, s[1] * es, s[2] * es, s[3] * es, 4, 0)


def _flat(t: Tensor | None, inner: int = 1) -> tuple:
    return L.NULL if t is None else L.arr(t, inner)


class _Photometric(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, window, w_l1, w_ssim, w_0, need_a, need_b):
        tg = L.target(a)
        s = L.scalar_of(a.dtype)
        n = a.numel()
        radius = window.numel() // 2
        both = bool(need_b)
        k = 4 if both else 3
        opts = dict(dtype=a.dtype, device=a.device)
        moments = torch.empty(n * 5, **opts)
        partials = torch.empty(n * k, **opts) if (need_a or need_b) else None
        ia, ib, wd = _image(a), _image(b), L.arr(window)
        runs = cpu_threads.element_runs(tg, None, n)
        cpu_threads.launch_runs(K.rows_kernel(s, radius), (), runs, [*ia, *ib, *wd, *L.arr(moments, 5)], tg)
        loss = L.zeros((len(runs),), torch.float64, tg)
        kern = K.cols_kernel(s, radius, both)
        head = [*L.arr(moments, 5), *ia, *ib, *wd, *_flat(partials, k)]
        tail = [n, w_l1 / n, w_ssim / n, float(w_0)]
        if tg.cpu:  # one accumulator per run (the runs add side by side), summed below
            cpu_threads.run([partial(L.launch, kern, end - first, head + [*L.at(loss.data_ptr() + 8 * r, 1, 8),
                                                                         *tail, first], tg)
                             for r, (first, end) in enumerate(runs)])
            total = loss.sum() if len(runs) > 1 else loss[0]
        else:  # whole blocks (the block sum): threads past n add nothing
            L.launch(kern, -(-n // K.BLOCK) * K.BLOCK, head + [*L.arr(loss), *tail, 0], tg, None, K.BLOCK)
            total = loss[0]
        if partials is not None:
            ctx.save_for_backward(a, b, window, partials)
            ctx.grads = (w_ssim / n, w_l1 / n, bool(need_a), both)
        return total.to(a.dtype)

    @staticmethod
    def backward(ctx, g):
        a, b, window, partials = ctx.saved_tensors
        g_ssim, g_l1, need_a, both = ctx.grads
        tg = L.target(a)
        s = L.scalar_of(a.dtype)
        n = a.numel()
        _, H, W, C = a.shape
        radius = window.numel() // 2
        k = 4 if both else 3
        wd = L.arr(window)
        runs = cpu_threads.element_runs(tg, None, n)
        t = torch.empty_like(partials)
        cpu_threads.launch_runs(K.cols_adjoint_kernel(s, radius, both), (), runs,
                                [*L.arr(partials, k), *wd, *L.arr(t, k), H, W, C], tg)
        ga = torch.empty(a.shape, dtype=a.dtype, device=a.device) if need_a else None
        gb = torch.empty(b.shape, dtype=b.dtype, device=b.device) if both else None
        go = g.detach().reshape(1).to(a.dtype).contiguous()
        cpu_threads.launch_runs(K.rows_adjoint_kernel(s, radius, both), (), runs,
                                [*L.arr(t, k), *wd, *_image(a), *_image(b), *L.arr(go), *_flat(ga), *_flat(gb),
                                 g_ssim, g_l1], tg)
        return ga, gb, None, None, None, None, None, None


def photometric_warp(a: Tensor, b: Tensor, w_l1: float, w_ssim: float, w_0: float, window: Tensor) -> Tensor:
    """``w_0 + mean over pixels and channels of (w_l1 |a - b| + w_ssim SSIM(a, b))`` of two image
    batches ``[V, H, W, C]`` (or ``[H, W, C]``), float32 or float64, on the CPU or CUDA, in the
    Warp kernels, differentiable in both images. SSIM: ``window`` (odd length, normalised) applied
    separably with reflected borders, constants ``0.01^2`` and ``0.03^2`` (as
    ``ssgwarp.services.losses.ssim_map``). The 3DGS loss ``(1 - l) L1 + l (1 - SSIM)`` is
    ``w_l1 = 1 - l, w_ssim = -l, w_0 = l``; the mean SSIM ``0, 1, 0``. The sum is accumulated in
    float64 (on CUDA in an order that varies from run to run at that precision's last bits; the
    gradient does not depend on it)."""
    if a.shape != b.shape or a.ndim not in (3, 4):
        raise ValueError(f"photometric: expected two [V, H, W, C] (or [H, W, C]) images of one shape, got "
                         f"{tuple(a.shape)} and {tuple(b.shape)}")
    if a.device != b.device:
        raise ValueError(f"photometric: the images are on different devices ({a.device} and {b.device})")
    if a.numel() == 0:
        raise ValueError(f"photometric: empty images {tuple(a.shape)}")
    if window.ndim != 1 or window.numel() % 2 != 1:
        raise ValueError(f"photometric: the window must be 1-D of odd length, got {tuple(window.shape)}")
    if a.ndim == 3:
        a, b = a[None], b[None]
    dt = torch.promote_types(a.dtype, b.dtype)
    a, b = a.to(dt), b.to(dt)
    L.scalar_of(dt)  # (float32 and float64 only: a clear error for others)
    window = L.dense(window.detach().to(device=a.device, dtype=dt))
    need_a = a.requires_grad and torch.is_grad_enabled()
    need_b = b.requires_grad and torch.is_grad_enabled()
    return L.apply(_Photometric, a, b, window, float(w_l1), float(w_ssim), float(w_0), need_a, need_b,
                   needs_grad=need_a or need_b)
