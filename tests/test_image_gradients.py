"""The blending backward reads the images' incoming gradients in place, whatever their layout.

A loss such as ``image.sum()`` hands the backward a gradient expanded from a scalar (every stride
0), a loss on ``image.permute(0, 3, 1, 2)`` one with channels first; the kernel reads those through
their strides (``ssgwarp.raster.launch.pixel_rows``) and only copies layouts whose pixel axes do not
merge. Every layout must give the gradients a contiguous copy of the same values gives, to the bit.
"""
import pytest
import torch

from ssgwarp import rasterization
from ssgwarp.raster import launch as L

from conftest import CUDA_ONLY
from test_rasterizer import make_cameras, make_scene

DEVICES = ["cpu", pytest.param("cuda", marks=CUDA_ONLY)]


def grads(params, vm, K, w, h, loss, device):
    """Gradients of every input and of the screen means (deterministic: bit-comparable on CUDA,
    where the default backward's atomic sums vary in order from run to run)."""
    leaves = [p.to(device).clone().requires_grad_(True) for p in params]
    img, alpha, meta = rasterization(*leaves, vm.to(device), K.to(device), w, h, deterministic=True)
    meta["means2d"].retain_grad()
    loss(img, alpha).backward()
    return [p.grad for p in leaves] + [meta["means2d"].grad]


def weights(shape, seed, dtype):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cams", [1, 2])
def test_every_gradient_layout_gives_the_contiguous_gradients(device, cams):
    dt = torch.float32
    w, h = 40, 28
    params = make_scene(150, dt, seed=4)
    vm, K = make_cameras(cams, w, h, dt)
    wc = weights((cams, 3, h, w), 1, dt).to(device)  # channels first
    wa = weights((cams, h, w, 1), 2, dt).to(device)
    losses = {
        # expanded from a scalar (strides 0) / a contiguous copy of the same ones
        "sum": (lambda img, a: img.sum() + a.sum(),
                lambda img, a: (img * torch.ones_like(img)).sum() + (a * torch.ones_like(a)).sum()),
        # channels first (merges in place with one camera, copied with two)
        "permuted": (lambda img, a: (img.permute(0, 3, 1, 2) * wc).sum() + (a * wa).sum(),
                     lambda img, a: (img * wc.permute(0, 2, 3, 1).contiguous()).sum() + (a * wa).sum()),
        # every other row of the image: pixel axes that never merge
        "rows": (lambda img, a: (img[:, ::2] * wc.permute(0, 2, 3, 1)[:, ::2]).sum(),
                 lambda img, a: (img * torch.zeros_like(img).index_copy(
                     1, torch.arange(0, h, 2, device=img.device),
                     wc.permute(0, 2, 3, 1)[:, ::2].contiguous())).sum()),
    }
    for name, (strided, dense) in losses.items():
        a = grads(params, vm, K, w, h, strided, device)
        b = grads(params, vm, K, w, h, dense, device)
        for x, y in zip(a, b):
            assert torch.equal(x, y), name


def test_pixel_rows_reads_in_place_where_the_pixel_axes_merge():
    img = torch.zeros(1, 6, 5, 3)
    ones = torch.ones(()).expand(2, 6, 5, 3)  # the gradient of image.sum()
    desc, kept = L.pixel_rows(ones, 3)
    assert kept is ones and desc[2:4] == (60, 3) and desc[6:8] == (0, 0)
    first = torch.zeros(1, 3, 6, 5).permute(0, 2, 3, 1)  # channels first, one camera
    desc, kept = L.pixel_rows(first, 3)
    assert kept is first and desc[6:8] == (4, 4 * 30)
    rows = img[:, ::2]  # every other row: copied
    desc, kept = L.pixel_rows(rows, 3)
    assert kept is not rows and kept.is_contiguous() and desc[6:8] == (12, 4)
    alpha = torch.ones(()).expand(2, 6, 5, 1)
    desc, kept = L.pixel_rows(alpha, 1)
    assert kept is alpha and desc[10] == 1 and desc[6] == 0
    assert L.pixel_rows(None, 3) == (L.NULL, None)
