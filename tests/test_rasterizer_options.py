"""Every option of ``ssgwarp.rasterization`` exercised: its documented effect, and the Warp kernels
against the torch reference (images and every gradient, entry by entry) with the option set.

Options: near/far planes, radius_clip, eps2d, each render mode with backgrounds, SH degrees 1 and 2,
per-camera SH and colours ``[C, N, ...]``, tile sizes, several cameras in one call.
"""
from __future__ import annotations

import pytest
import torch

from ssgwarp import rasterization

from conftest import CUDA_ONLY, assert_close_elementwise
from test_rasterizer import assert_match, make_cameras, make_scene, run_both

F64 = torch.float64
W, H = 36, 28


def on_axis_scene(n: int, seed: int, z_range=(2.0, 6.0)):
    """``n`` Gaussians in front of an identity camera, depths spread over ``z_range``."""
    g = torch.Generator().manual_seed(seed)
    means = torch.stack([torch.rand(n, generator=g, dtype=F64) * 1.6 - 0.8,
                         torch.rand(n, generator=g, dtype=F64) * 1.2 - 0.6,
                         torch.rand(n, generator=g, dtype=F64) * (z_range[1] - z_range[0]) + z_range[0]], -1)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.12 + 0.01
    opac = torch.rand(n, generator=g, dtype=F64) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=F64)
    vm = torch.eye(4, dtype=F64)[None]
    K = torch.tensor([[[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]]], dtype=F64)
    return [means, quats, scales, opac, colors], vm, K


def no_bg_grad(out):
    for d in out.values():
        d[2].append(torch.zeros(1))  # no background gradient to compare
    return out


def render(params, vm, K, **kw):
    return rasterization(*params, vm, K, W, H, **kw)


def subset(params, keep):
    return [p[keep] for p in params]


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_near_and_far_planes_cull_by_camera_depth(backend):
    params, vm, K = on_axis_scene(80, seed=1)
    z = params[0][:, 2]
    near, far = 3.0, 5.0
    img, alpha, meta = render(params, vm, K, near_plane=near, far_plane=far, backend=backend)
    inside = (z >= near) & (z <= far)
    drawn = (meta["radii"][0] > 0).all(-1)
    assert not drawn[~inside].any() and drawn[inside].sum() > 10 and (~inside).sum() > 10
    assert (meta["depths"][0][~inside] == 0).all()
    # the same image as the Gaussians inside the planes rendered with the default planes
    ref_img, ref_alpha, _ = render(subset(params, inside), vm, K, backend=backend)
    assert (img - ref_img).abs().max() < 1e-12 and (alpha - ref_alpha).abs().max() < 1e-12
    assert (img - render(params, vm, K, backend=backend)[0]).abs().max() > 0.05   # the planes did something
    if backend == "warp":
        assert_match(no_bg_grad(run_both(params, vm, K, W, H, near_plane=near, far_plane=far)), 1e-10, 1e-9)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_radius_clip_culls_small_gaussians(backend):
    params, vm, K = on_axis_scene(80, seed=2)
    radii = render(params, vm, K, backend=backend)[2]["radii"][0]
    clip = float(radii.max(-1).values.float().median())
    img, alpha, meta = render(params, vm, K, radius_clip=clip, backend=backend)
    small = (radii <= clip).all(-1)                  # both radii within the clip
    drawn = (meta["radii"][0] > 0).all(-1)
    assert torch.equal(drawn, (radii > 0).all(-1) & ~small)
    assert small.sum() > 10 and drawn.sum() > 10
    ref_img, _, _ = render(subset(params, ~small), vm, K, backend=backend)
    assert (img - ref_img).abs().max() < 1e-12
    if backend == "warp":
        assert_match(no_bg_grad(run_both(params, vm, K, W, H, radius_clip=clip)), 1e-10, 1e-9)


@pytest.mark.parametrize("eps2d,mode", [(0.0, "classic"), (0.1, "classic"), (1.0, "classic"), (0.1, "antialiased"),
                                        (1.0, "antialiased")])
def test_eps2d_against_reference(eps2d, mode):
    params = make_scene(100, seed=3)
    vm, K = make_cameras(2, W, H)
    out = run_both(params, vm, K, W, H, eps2d=eps2d, rasterize_mode=mode,
                   backgrounds=torch.tensor([[0.2, 0.4, 0.6], [1.0, 0.5, 0.0]], dtype=F64))
    assert_match(out, 1e-10, 1e-9)
    # a larger blur spreads every Gaussian: more pixels touched than with the default 0.3
    if eps2d == 1.0 and mode == "classic":
        base = rasterization(*params, vm, K, W, H)[2]["radii"]
        assert (out["warp"][3]["radii"] >= base).all() and (out["warp"][3]["radii"] > base).any()


@pytest.mark.parametrize("mode", ["D", "ED", "RGB+D", "RGB+ED"])
def test_depth_modes_with_backgrounds_against_reference(mode):
    params = make_scene(120, seed=4)
    vm, K = make_cameras(2, W, H)
    bg = torch.tensor([[0.2, 0.4, 0.6], [1.0, 0.5, 0.0]], dtype=F64)
    out = run_both(params, vm, K, W, H, render_mode=mode, backgrounds=bg)
    img, alpha = out["warp"][0], out["warp"][1]
    assert img.shape[-1] == (1 if mode in ("D", "ED") else 4)
    if mode.startswith("RGB"):
        empty = alpha[..., 0] == 0
        assert empty.any() and torch.equal(img[..., :3][empty], bg[:, None, None].expand(-1, H, W, -1)[empty])
        assert (img[..., 3][empty] == 0).all()   # the depth channel takes no background
    if mode in ("D", "ED"):
        # the background's gradient flows nowhere: depth images ignore it
        for d in out.values():
            assert d[2][-1] is None or not d[2][-1].any()
            d[2][-1] = torch.zeros(1)
    assert_match(out, 1e-10, 1e-9)


@pytest.mark.parametrize("degree", [1, 2])
def test_sh_degrees_1_and_2_against_reference(degree):
    means, quats, scales, opac, _ = make_scene(100, seed=5)
    g = torch.Generator().manual_seed(5)
    sh = torch.randn(100, (degree + 1) ** 2 + 2, 3, generator=g, dtype=F64) * 0.4  # extra bands are ignored
    vm, K = make_cameras(2, W, H)
    out = no_bg_grad(run_both([means, quats, scales, opac, sh], vm, K, W, H, sh_degree=degree))
    assert_match(out, 1e-10, 1e-9)
    # the view direction matters: the two cameras see a Gaussian's colour differently
    img = rasterization(means, quats, scales, opac, sh, vm, K, W, H, sh_degree=degree)[0]
    img0 = rasterization(means, quats, scales, opac, sh[:, :1], vm, K, W, H, sh_degree=0)[0]
    assert (img - img0).abs().max() > 0.05
    # bands above the degree have no gradient
    assert not out["warp"][2][4][:, (degree + 1) ** 2:].any()


@pytest.mark.parametrize("kind", ["colors", "sh"])
def test_per_camera_colours_equal_each_camera_alone(kind):
    """``colors [C, N, D]`` (or SH ``[C, N, K, 3]``): camera c renders with its own slice, as if
    rendered alone with ``[N, D]``; gradients against the reference."""
    means, quats, scales, opac, _ = make_scene(90, seed=6)
    vm, K = make_cameras(3, W, H)
    g = torch.Generator().manual_seed(6)
    cols = torch.rand(3, 90, 2, generator=g, dtype=F64) if kind == "colors" else \
        torch.randn(3, 90, 4, 3, generator=g, dtype=F64) * 0.4
    kw = {} if kind == "colors" else {"sh_degree": 1}
    img, alpha, _ = rasterization(means, quats, scales, opac, cols, vm, K, W, H, **kw)
    for c in range(3):
        one, one_alpha, _ = rasterization(means, quats, scales, opac, cols[c], vm[c:c + 1], K[c:c + 1], W, H, **kw)
        assert (img[c:c + 1] - one).abs().max() < 1e-12 and (alpha[c:c + 1] - one_alpha).abs().max() < 1e-12
    assert (img[0] - img[1]).abs().max() > 0.05
    bg = torch.rand(3, cols.shape[-1] if kind == "colors" else 3, generator=g, dtype=F64)
    out = run_both([means, quats, scales, opac, cols], vm, K, W, H, backgrounds=bg, **kw)
    assert_match(out, 1e-10, 1e-9)


@pytest.mark.parametrize("tile", [4, 8, 32, 64])
def test_tile_sizes_give_the_same_image(tile):
    """The tile size only groups pixels: every pixel a Gaussian reaches with alpha >= 1/255 lies in its
    tile box, so images equal the default tile's; gradients against the reference at that tile."""
    params = make_scene(120, seed=7)
    vm, K = make_cameras(2, W, H)
    base, base_alpha, _ = rasterization(*params, vm, K, W, H)
    img, alpha, meta = rasterization(*params, vm, K, W, H, tile_size=tile)
    assert (img - base).abs().max() < 1e-12 and (alpha - base_alpha).abs().max() < 1e-12
    assert meta["tile_width"] == -(-W // tile) and meta["isect_offsets"].shape == (2, -(-H // tile), -(-W // tile))
    if tile in (8, 32):
        out = run_both(params, vm, K, W, H, tile_size=tile, backgrounds=torch.full((2, 3), 0.5, dtype=F64))
        assert_match(out, 1e-10, 1e-9)


def test_several_cameras_in_one_call_equal_separate_calls():
    """C cameras in one call: each image equals that camera rendered alone, and every gradient is the
    sum of the single-camera gradients."""
    params = make_scene(100, seed=8)
    vm, K = make_cameras(3, W, H)
    g = torch.Generator().manual_seed(8)
    wts = torch.randn(3, H, W, 3, generator=g, dtype=F64)

    def grads(vms, Ks, w):
        leaves = [p.clone().requires_grad_(True) for p in params]
        img, alpha, _ = rasterization(*leaves, vms, Ks, W, H)
        ((img * w).sum() + alpha.sum()).backward()
        return img.detach(), [p.grad for p in leaves]

    img, together = grads(vm, K, wts)
    alone = [grads(vm[c:c + 1], K[c:c + 1], wts[c:c + 1]) for c in range(3)]
    for c in range(3):
        assert (img[c] - alone[c][0][0]).abs().max() < 1e-12
    for i, gr in enumerate(together):
        assert_close_elementwise(gr, sum(a[1][i] for a in alone), 1e-10, 1e-12, f"gradient {i}", ulps=16)


def test_exact_settings_turn_every_shortcut_off():
    """``RasterSettings.exact``: no alpha threshold, no cut-off, no clamp, a fixed extent of ``sigma_max``,
    IEEE maths, the cancellation-free covariance; each differs from the default (gsplat's) settings."""
    from ssgwarp import RasterSettings

    fields = ("alpha_min", "t_min", "alpha_max", "extent", "sigma_max", "fast_math", "covariance")
    e, d = RasterSettings.exact(), RasterSettings()
    assert tuple(getattr(e, f) for f in fields) == (0.0, 0.0, 1.0, "fixed", 3.33, False, "factor")
    assert tuple(getattr(d, f) for f in fields) == (1.0 / 255.0, 1e-4, 0.999, "opacity", 3.33, True, "gsplat")
    assert RasterSettings.exact(5.0).sigma_max == 5.0


def test_for_dtype_raises_t_min_to_the_precision_floor_only():
    """``for_dtype``: a cut-off below the type's floor (1e-20 float32, 1e-200 float64) is raised to it, nothing
    else changes; a cut-off at or above the floor, and types without a floor, keep the settings."""
    import dataclasses

    from ssgwarp import RasterSettings

    e = RasterSettings.exact()
    assert e.for_dtype(torch.float32) == dataclasses.replace(e, t_min=1e-20)
    assert e.for_dtype(torch.float64) == dataclasses.replace(e, t_min=1e-200)
    assert e.for_dtype(torch.float16) == e
    d = RasterSettings()
    assert d.for_dtype(torch.float32) == d and d.for_dtype(torch.float64) == d
    at = RasterSettings(t_min=1e-20)
    assert at.for_dtype(torch.float32) == at


def test_incoming_gradients_of_any_layout_give_the_same_gradients():
    """The ops read incoming gradients in place where their rows are strided views and copy them otherwise:
    a broadcast gradient (``.sum()``: stride 0) and a column-strided one (a transposed tensor) give the
    gradients of the same gradient made contiguous, for the SH op and for a loss on the projected
    Gaussians of ``meta`` (means2d, depths, conics, opacities)."""
    from ssgwarp.raster.sh_ops import spherical_harmonics_warp

    g = torch.Generator().manual_seed(5)
    dirs = torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    coeffs = torch.randn(2, 30, 16, 3, generator=g, dtype=torch.float64)
    strided = torch.randn(3, 2, 30, generator=g, dtype=torch.float64).permute(1, 2, 0)
    assert strided.reshape(60, 3).stride(1) != 1

    def sh_grads(upstream):
        d, c = dirs.clone().requires_grad_(True), coeffs.clone().requires_grad_(True)
        y = spherical_harmonics_warp(3, d, c)
        if upstream is None:
            y.sum().backward()
        else:
            y.backward(upstream)
        return d.grad, c.grad

    for upstream, same in ((None, torch.ones(2, 30, 3, dtype=torch.float64)), (strided, strided.contiguous())):
        for a, b in zip(sh_grads(upstream), sh_grads(same)):
            assert torch.equal(a, b)

    means, quats, scales, opac, colors = make_scene(40, dtype=torch.float64)
    vm, K = make_cameras(2, 24, 24, dtype=torch.float64)

    def meta_grads(contiguous):
        p = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac)]
        _, _, meta = rasterization(*p, colors, vm, K, 24, 24)
        loss = 0.0
        for key in ("means2d", "depths", "conics", "opacities"):
            loss = loss + ((meta[key] * torch.ones_like(meta[key])).sum() if contiguous else meta[key].sum())
        loss.backward()
        return [t.grad for t in p]

    for a, b in zip(meta_grads(False), meta_grads(True)):
        assert b.abs().max() > 0 and torch.equal(a, b)


def test_backward_launch_blocks_by_device_and_tile_size():
    """``backward_blocks(tile_size, deterministic, cpu) -> (per_warp, block_dim)`` by hand: CPU, one pixel per
    block (deterministic too: its slots are then written tile by tile, pixel after pixel); CUDA deterministic,
    one block per tile; else the largest multiple of 32 up to 256 dividing the tile's pixels, summed per warp,
    or one tile row per block when the tile is not whole warps."""
    from ssgwarp.raster.blend_ops import backward_blocks

    assert backward_blocks(16, True, False) == (False, 256) and backward_blocks(8, True, True) == (True, 1)
    assert backward_blocks(16, False, True) == (True, 1)
    assert backward_blocks(16, False, False) == (True, 256)
    assert backward_blocks(8, False, False) == (True, 64)
    assert backward_blocks(24, False, False) == (True, 192)     # 576 pixels: 192 divides, 224 and 256 do not
    assert backward_blocks(40, False, False) == (True, 160)     # 1600 pixels: 160, a multiple of 32 (not 200)
    assert backward_blocks(4, False, False) == (False, 4)       # 16 pixels: half a warp
    assert backward_blocks(12, False, False) == (False, 12)     # 144 pixels: not a multiple of 32


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA_ONLY)])
@pytest.mark.parametrize("deterministic", [False, True])
def test_colour_only_backward_equals_the_full_backward(deterministic, device):
    """With nothing upstream of the splats wanting a gradient (a frozen scene's colours or
    identities trained), the backward runs its colour-only variant: the colour gradients are
    bit-identical to those of the full backward (geometry wanting gradients), for 20 channels, a
    background and a loss on the alpha; the geometry gets no gradient."""
    means, quats, scales, opac, _ = (t.to(device) for t in make_scene(60))
    vm, K = (t.to(device) for t in make_cameras(2, W, H))
    g = torch.Generator().manual_seed(8)
    colors = torch.randn(2, 60, 20, generator=g, dtype=means.dtype).to(device)
    bg = torch.rand(2, 20, generator=g, dtype=means.dtype).to(device)
    weight = torch.randn(2, H, W, 20, generator=g, dtype=means.dtype).to(device)
    out = []
    for geometry in (True, False):
        m, c = means.clone().requires_grad_(geometry), colors.clone().requires_grad_(True)
        img, alpha, _ = rasterization(m, quats, scales, opac, c, vm, K, W, H, backgrounds=bg,
                                      deterministic=deterministic)
        ((img * weight).sum() + alpha.square().sum()).backward()
        out.append((img.detach(), c.grad, m.grad))
    (img_full, g_full, gm_full), (img_col, g_col, gm_col) = out
    assert torch.equal(img_full, img_col)
    assert g_full.abs().max() > 0
    if deterministic or device == "cpu":
        assert torch.equal(g_full, g_col)
    else:  # (CUDA atomics add the blocks' sums in any order)
        torch.testing.assert_close(g_col, g_full, rtol=1e-9, atol=1e-12 * float(g_full.abs().max()))
    assert gm_full.abs().max() > 0 and gm_col is None
