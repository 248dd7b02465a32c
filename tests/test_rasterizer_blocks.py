"""The blending forward with one block per tile (``kernels/blend_forward.py: batched_forward_kernel``).

On CUDA it replaces the per-pixel walk: the tile's next projected Gaussians are loaded into shared
memory together, read through the sorted ids when no backward can follow (no per-intersection
gather at all) or from the gathered arrays when one can. It must be the same image, to the bit,
as the per-pixel walk (same rule, order and roundings), and the same gradients. The CPU runs the
per-pixel walk by default; here the block kernels are also run on Warp's CPU device (one thread
per block: the block vote is the thread's own flag), so their logic is tested wherever the suite
runs, and on CUDA (``-m cuda``) against the per-pixel walk there.
"""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
import warp as wp

from ssgwarp import RasterSettings, rasterization
from ssgwarp.kernels import blend_backward, blend_forward
from ssgwarp.raster import blend_ops as ops, launch as L

from conftest import CUDA_ONLY
from test_rasterizer import make_cameras, make_scene

DEVICES = ["cpu", pytest.param("cuda", marks=CUDA_ONLY)]


@pytest.fixture
def blocks_everywhere(monkeypatch):
    """Let the block kernels run on the CPU too (the rule otherwise keeps them to CUDA)."""
    rule = ops.batched
    monkeypatch.setattr(ops, "batched",
                        lambda tg, packed, tile_size: rule(SimpleNamespace(cpu=False), packed, tile_size))


def render(params, vm, K, w, h, grad, bg=None, **kw):
    """Image, alpha and (with ``grad``) the gradients of every input, the screen means included."""
    leaves = [p.clone().requires_grad_(grad) for p in params]
    bgl = None if bg is None else bg.clone().requires_grad_(grad)
    with torch.set_grad_enabled(grad):
        img, alpha, meta = rasterization(*leaves, vm, K, w, h, backgrounds=bgl, **kw)
    if not grad:
        return [img, alpha, meta["radii"]]
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(3)
    wi = torch.randn(img.shape, generator=g, dtype=img.dtype).to(img.device)
    wa = torch.randn(alpha.shape, generator=g, dtype=img.dtype).to(img.device)
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    return [img.detach(), alpha.detach()] + [p.grad for p in leaves] + [meta["means2d"].grad] + (
        [bgl.grad] if bgl is not None else [])


CASES = [  # (tile size, cameras, SH degree, backgrounds, dtype)
    (16, 1, None, False, torch.float32),
    (16, 3, None, True, torch.float32),  # colours shared by the cameras: ids c*N + g
    (8, 2, 3, False, torch.float32),  # SH: colours per camera
    (12, 2, None, True, torch.float64),  # 144-thread blocks (warps straddle tiles)
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("grad", [False, True], ids=["no-grad", "grad"])
@pytest.mark.parametrize("tile,cams,sh,with_bg,dtype", CASES)
def test_block_kernels_equal_the_per_pixel_walk(blocks_everywhere, monkeypatch, device, grad, tile, cams, sh,
                                                with_bg, dtype):
    w, h = 61, 45  # partial tiles at the right and bottom edges
    means, quats, scales, opac, colors = make_scene(300, dtype, seed=5, scale=0.25)
    if sh is not None:
        g = torch.Generator().manual_seed(6)
        colors = torch.cat([colors[:, None] / 0.28209479177387814,
                            0.3 * torch.randn(colors.shape[0], (sh + 1) ** 2 - 1, 3, generator=g, dtype=dtype)], 1)
    params = [t.to(device) for t in (means, quats, scales, opac, colors)]
    vm, K = (t.to(device) for t in make_cameras(cams, w, h, dtype))
    bg = torch.rand(cams, 3, dtype=dtype, generator=torch.Generator().manual_seed(7)).to(device) if with_bg else None
    # (the default backward's atomic adds sum in a varying order on CUDA: the fixed-order one here)
    kw = dict(tile_size=tile, sh_degree=sh, deterministic=grad)
    out = {}
    # the per-pixel walk; the block kernels reading the gather, and (both passes) through the ids
    for key, on, limit in (("walk", False, 0), ("gather", True, 0), ("ids", True, 1 << 62)):
        monkeypatch.setattr(ops, "BATCHED", on)
        monkeypatch.setattr(ops, "IDS_BACKWARD_MAX", limit)
        out[key] = render(params, vm, K, w, h, grad, bg, **kw)
    assert out["ids"][0].abs().sum() > 0 and (out["ids"][1] > 0.5).any()  # a scene that covers the image
    for key in ("gather", "ids"):
        for a, b in zip(out["walk"], out[key]):
            assert (a is None) == (b is None)
            if a is not None:
                assert torch.equal(a, b)


def test_gather_only_where_a_backward_can_follow(blocks_everywhere, monkeypatch):
    """No grad: the block kernel reads through the ids and nothing is gathered. With a gradient and
    more intersections than ``IDS_BACKWARD_MAX`` the gather runs once, in the forward, and the
    backward walks it (no second gather); up to it both passes read through the ids, no gather."""
    kernels = []
    real = L.launch

    def spy(kernel, *a, **k):
        kernels.append(kernel)  # (the objects: every variant of a kernel has one key)
        return real(kernel, *a, **k)

    monkeypatch.setattr(L, "launch", spy)
    params = list(make_scene(120, torch.float32, seed=2))
    vm, K = make_cameras(2, 40, 32, torch.float32)
    pack = blend_forward.pack_kernel(wp.float32, 3)
    through, gathered = (blend_forward.batched_forward_kernel(wp.float32, 3, True, 256, ids) for ids in (True, False))
    # (through the ids the colours' gradients also get rows of their own)
    backward = {ids: blend_backward.reduced_backward_kernel(wp.float32, 3, False, True, True, False, ids, ids)
                for ids in (True, False)}
    render(params, vm, K, 40, 32, grad=False, tile_size=16)
    assert pack not in kernels and through in kernels
    for limit, ids in ((0, False), (1 << 62, True)):
        monkeypatch.setattr(ops, "IDS_BACKWARD_MAX", limit)
        kernels.clear()
        render(params, vm, K, 40, 32, grad=True, tile_size=16)
        assert kernels.count(pack) == (0 if ids else 1)
        assert (through if ids else gathered) in kernels and backward[ids] in kernels
        assert backward[not ids] not in kernels


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cams,shared,tile", [(1, True, 16), (3, True, 16), (2, False, 16), (2, True, 12)])
def test_reads_through_the_ids_give_the_gathers_gradients(blocks_everywhere, monkeypatch, device, cams, shared, tile):
    """The default (non-deterministic) backward through the ids, its colours' gradients in rows of
    their own, against the gather's packed rows: the same gradients (bit-equal on the CPU, where the
    adds run in one order; to rounding on CUDA, whose atomic adds do not), for colours shared by the
    cameras and per camera, with sums per warp (tile 16) and per block (tile 12, on CUDA); and the
    colours' gradient contiguous as autograd keeps it."""
    dt = torch.float32 if device == "cuda" else torch.float64
    means, quats, scales, opac, colors = make_scene(200, dt, seed=8, scale=0.25)
    if not shared:
        colors = torch.rand(cams, 200, 3, dtype=dt, generator=torch.Generator().manual_seed(9))
    params = [t.to(device) for t in (means, quats, scales, opac, colors)]
    vm, K = (t.to(device) for t in make_cameras(cams, 45, 37, dt))
    out = {}
    for limit in (0, 1 << 62):
        monkeypatch.setattr(ops, "IDS_BACKWARD_MAX", limit)
        out[limit] = render(params, vm, K, 45, 37, True, settings=RasterSettings(cpu_threads=1), tile_size=tile)
    for a, b in zip(out[0], out[1 << 62]):
        assert a.abs().sum() > 0
        if device == "cpu":
            assert torch.equal(a, b)
        else:
            assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)
    assert out[1 << 62][6].is_contiguous() and out[1 << 62][6].shape == colors.shape


def test_block_kernels_only_on_cuda_with_packed_splats_and_tiles_of_one_block():
    cpu = L.target(torch.zeros(1))
    packed = torch.zeros(1, 1, 6)
    assert not ops.batched(cpu, packed, 16)  # the CPU walks per pixel
    cuda = SimpleNamespace(cpu=False)
    assert ops.batched(cuda, packed, 16) and ops.batched(cuda, packed, 32)
    assert not ops.batched(cuda, packed, 33)  # 1089 threads: more than a block holds
    assert not ops.batched(cuda, None, 16)  # no packed splats to read
