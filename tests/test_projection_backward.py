"""The hand-written projection backward (``kernels/projection_backward.py``).

Held to finite differences (float64, CPU, ``gradcheck`` of the projection alone: screen means,
depths, conics and opacities to means, quaternions, scales, opacities and view matrices; both
covariance forms, classic and antialiased, a Gaussian where the Jacobian clamps), and to Warp's
generated adjoint of the forward kernel (``ops.HAND_BACKWARD = False``) through whole renders: SH
colours (whose backward writes the means' slots first), several cameras, culled Gaussians, depth
modes; float64 to rounding, float32 within a few ulps; on the CPU and, with ``-m cuda``, on CUDA.
"""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp import RasterSettings, rasterization
from ssgwarp.raster import ops

from conftest import CUDA_ONLY

F64 = torch.float64
W, H = 40, 30
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA_ONLY)]


def cameras(C, dtype, device="cpu"):
    vms = []
    for c in range(C):
        a = 0.15 * c + 0.05
        vm = torch.eye(4, dtype=dtype)
        vm[0, 0], vm[0, 2], vm[2, 0], vm[2, 2] = math.cos(a), math.sin(a), -math.sin(a), math.cos(a)
        vm[:3, 3] = torch.tensor([0.1 * c - 0.1, -0.05, 0.3], dtype=dtype)
        vms.append(vm)
    K = torch.tensor([[32.0, 0, W / 2 + 1], [0, 30.0, H / 2 - 1], [0, 0, 1]], dtype=dtype)
    return torch.stack(vms).to(device), K.expand(C, 3, 3).contiguous().to(device)


def scene(N, dtype, seed, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(N, 3, generator=g, dtype=dtype) * 0.9
    means[:, 2] += 4.0
    means[0] = torch.tensor([2.0, 0.2, 2.0], dtype=dtype)  # off to the side: the Jacobian clamps
    means[1] = torch.tensor([0.0, 0.0, -1.0], dtype=dtype)  # behind the camera: culled
    quats = torch.randn(N, 4, generator=g, dtype=dtype)
    scales = torch.rand(N, 3, generator=g, dtype=dtype) * 0.25 + 0.02
    scales[0] = torch.tensor([0.4, 0.3, 0.35], dtype=dtype)  # (large enough to reach into the image)
    opac = torch.rand(N, generator=g, dtype=dtype) * 0.85 + 0.1
    return [t.to(device) for t in (means, quats, scales, opac)]


@pytest.mark.parametrize("covariance", ["gsplat", "factor"])
@pytest.mark.parametrize("antialiased", [False, True])
def test_projection_backward_matches_finite_differences(covariance, antialiased):
    """Every output of the projection (screen means, depths, conics, opacities) against every
    differentiable input, including the view matrices of two cameras, in float64."""
    means, quats, scales, opac = scene(5, F64, seed=3)
    vm, K = cameras(2, F64)
    settings = RasterSettings.exact()
    settings = RasterSettings(**{**settings.__dict__, "covariance": covariance})
    # the clamped Gaussian is visible in the first camera, and its clamp is in play there
    radii, m2, *_ = ops.project_warp(means, quats, scales, opac, vm, K, W, H, settings=settings)
    assert (radii[0, 0] > 0).all() and (radii[:, 1] == 0).all()
    p0 = vm[0, :3, :3] @ means[0] + vm[0, :3, 3]
    assert p0[0] / p0[2] > (W - K[0, 0, 2]) / K[0, 0, 0] + 0.3 * 0.5 * W / K[0, 0, 0]

    def f(means, quats, scales, opac, vm):
        _, m2, depths, conics, op = ops.project_warp(means, quats, scales, opac, vm, K, W, H,
                                                     antialiased=antialiased, settings=settings)
        return m2, depths, conics, op

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, vm)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def _grads(hand, params, colors, vm, K, monkeypatch, **kw):
    monkeypatch.setattr(ops, "HAND_BACKWARD", hand)
    leaves = [t.clone().requires_grad_(True) for t in (*params, colors, vm)]
    img, alpha, meta = rasterization(*leaves[:5], leaves[5], K, W, H, **kw)
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(5)
    wi = torch.randn(img.shape, generator=g, dtype=img.dtype).to(img.device)
    wa = torch.randn(alpha.shape, generator=g, dtype=img.dtype).to(img.device)
    # the depths and conics in meta take part too (a loss may read them)
    loss = (img * wi).sum() + (alpha * wa).sum() + 0.01 * meta["depths"].sum() + 0.1 * meta["conics"].sum()
    loss.backward()
    return [t.grad for t in leaves]


CASES = [  # (cameras, SH degree, rasterize mode, render mode, covariance)
    (1, None, "classic", "RGB", "gsplat"),
    (3, None, "antialiased", "RGB+ED", "gsplat"),
    (2, 2, "classic", "RGB", "gsplat"),  # SH: the colour backward writes the means' slots first
    (1, 3, "antialiased", "D", "factor"),
    (3, None, "classic", "RGB+D", "factor"),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("case", CASES)
def test_hand_backward_matches_warp_adjoint(case, dtype, device, monkeypatch):
    """Whole renders: the gradients of means, quaternions, scales, opacities, colours and view
    matrices with the hand kernel against Warp's generated adjoint of the forward."""
    C, degree, raster_mode, render_mode, covariance = case
    params = scene(60, dtype, seed=C + (degree or 0), device=device)
    vm, K = cameras(C, dtype, device)
    g = torch.Generator().manual_seed(9)
    colors = (torch.rand(60, (degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.4 if degree is not None
              else torch.rand(60, 3, generator=g, dtype=dtype)).to(device)
    kw = dict(sh_degree=degree, rasterize_mode=raster_mode, render_mode=render_mode,
              settings=RasterSettings(covariance=covariance))
    hand = _grads(True, params, colors, vm, K, monkeypatch, **kw)
    warp = _grads(False, params, colors, vm, K, monkeypatch, **kw)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors", "viewmats"], hand, warp):
        if name == "colors" and render_mode == "D":  # (depth alone: the colours are not used)
            assert a is None and b is None
            continue
        assert b.abs().max() > 0, name  # every input's gradient is in play
        err = ((a - b).abs().max() / b.abs().max()).item()
        assert err < tol, (name, err)
