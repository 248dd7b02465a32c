"""Finite-difference checks (float64, CPU, ``torch.autograd.gradcheck``) of the Warp backend's
gradients where the reference comparison alone would pass a rule shared by both backends: SH colour
(degrees 1-3, through the view direction, so also to the view matrix), antialiased mode with
expected depth, and the blending op's own gradient to the screen-space means (``means2d``, what
densification reads), conics, colours, opacities and backgrounds.
"""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp import RasterSettings, rasterization
from ssgwarp.core.cameras import intrinsics

EXACT = RasterSettings.exact()
F64 = torch.float64
SIZE = 10


def small_scene(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor([[0.1, -0.05, 3.0], [-0.2, 0.1, 3.5], [0.05, 0.15, 4.0], [0.0, 0.0, 4.5]], dtype=F64)[:n]
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.3 + 0.4  # large: boxes cover the one tile
    opac = torch.rand(n, generator=g, dtype=F64) * 0.8 + 0.1
    vm = torch.eye(4, dtype=F64)[None].clone()
    vm[0, :3, 3] = torch.tensor([0.3, -0.2, 0.1], dtype=F64)   # the camera centre is not the origin
    angle = 0.2                                                  # and the camera is turned about y
    c, s = math.cos(angle), math.sin(angle)
    vm[0, 0, 0], vm[0, 0, 2], vm[0, 2, 0], vm[0, 2, 2] = c, s, -s, c
    vm[0, 2, 3] += 0.5
    K = intrinsics(8.0, 8.0, SIZE / 2, SIZE / 2, 1, dtype=F64)
    return g, [means, quats, scales, opac], vm, K


def check(f, inputs):
    assert torch.autograd.gradcheck(f, [t.clone().requires_grad_(True) for t in inputs], eps=1e-6, atol=1e-6,
                                    rtol=1e-4)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_gradcheck_sh(degree):
    """SH colour: gradients to the coefficients, to the means (view direction) and to the view matrix
    (camera centre) match finite differences."""
    g, (means, quats, scales, opac), vm, K = small_scene(3, seed=degree)
    sh = torch.randn(3, (degree + 1) ** 2, 3, generator=g, dtype=F64) * 0.5
    sh[:, 0] += 1.0                      # keep the colours above the clamp at 0 (a kink)
    bg = torch.tensor([[0.3, 0.7, 0.1]], dtype=F64)

    def f(means, opac, sh, vm, bg):
        img, alpha, _ = rasterization(means, quats, scales, opac, sh, vm, K, SIZE, SIZE, sh_degree=degree,
                                      settings=EXACT, backgrounds=bg, backend="warp")
        return img, alpha

    check(f, [means, opac, sh, vm, bg])


def test_gradcheck_antialiased_expected_depth():
    """Antialiased mode (opacity times the blur compensation) with RGB+ED (expected depth = D / alpha):
    every input, including the view matrix and the backgrounds."""
    g, (means, quats, scales, opac), vm, K = small_scene(4, seed=7)
    colors = torch.rand(4, 3, generator=g, dtype=F64)
    scales = scales * 0.1                # small Gaussians: the compensation is far from 1
    bg = torch.tensor([[0.2, 0.5, 0.9]], dtype=F64)

    def f(means, quats, scales, opac, colors, vm, bg):
        img, alpha, _ = rasterization(means, quats, scales, opac, colors, vm, K, SIZE, SIZE, settings=EXACT,
                                      rasterize_mode="antialiased", render_mode="RGB+ED", backgrounds=bg,
                                      backend="warp")
        return img, alpha

    _, _, meta = rasterization(means, quats, scales, opac, colors, vm, K, SIZE, SIZE, settings=EXACT,
                               rasterize_mode="antialiased")
    assert (meta["opacities"][0] < 0.9 * opac).all()      # the factor is in play
    check(f, [means, quats, scales, opac, colors, vm, bg])


def test_gradcheck_blending_to_means2d():
    """The blending op alone: gradients to the screen-space means (the densification statistic),
    conics, colours, opacities and backgrounds, for two cameras."""
    from ssgwarp.raster import blend_ops, ops

    g = torch.Generator().manual_seed(11)
    C, N, D = 2, 4, 2
    means2d = torch.rand(C, N, 2, generator=g, dtype=F64) * 6 + 2
    conics = torch.stack([torch.rand(C, N, generator=g, dtype=F64) * 0.3 + 0.2,
                          torch.rand(C, N, generator=g, dtype=F64) * 0.1 - 0.05,
                          torch.rand(C, N, generator=g, dtype=F64) * 0.3 + 0.2], -1)
    colors = torch.rand(C, N, D, generator=g, dtype=F64)
    opac = torch.rand(C, N, generator=g, dtype=F64) * 0.8 + 0.1
    bg = torch.rand(C, D, generator=g, dtype=F64)
    radii = torch.full((C, N, 2), SIZE, dtype=torch.int32)
    depths = torch.arange(1.0, N + 1, dtype=F64).expand(C, N).contiguous()
    tiles = ops.bin_tiles(means2d, radii, depths, 16, 1, 1)

    def f(means2d, conics, colors, opac, bg):
        return blend_ops.blend_warp(means2d, conics, colors, opac, bg, tiles, SIZE, SIZE, 16, EXACT)

    check(f, [means2d, conics, colors, opac, bg])
