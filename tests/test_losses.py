"""The 3DGS photometric loss, ``(1 - lambda) L1 + lambda (1 - SSIM)`` with lambda = 0.2 (Kerbl et al. 2023),
in ssgwarp.services.losses and in the callers that train with it (reconstruction, Stage 2 fine-tuning).

SSIM is recomputed here with kornia directly, and D-SSIM is pinned by a property that does not depend on
the SSIM implementation: an image against its negative has SSIM ~ -1, so ``1 - SSIM`` ~ 2 (a halved term
would give ~1)."""
from __future__ import annotations

import kornia
import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.capture.datasets import SceneData
from ssgwarp.services.losses import dssim, gaussian_window, photometric, ssim_map
from ssgwarp.raster.rendering import render as render_views
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction.trainer import Trainer
from ssgwarp.raster.scene import GaussianScene


def _ssim(a, b):
    return kornia.metrics.ssim(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2), 11, max_val=1.0, padding="same").mean()


def _images():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(1, 24, 32, 3, generator=g)
    b = (a + 0.3 * torch.rand(1, 24, 32, 3, generator=g) - 0.15).clamp(0, 1)
    return a, b


def test_dssim_is_one_minus_ssim():
    a, b = _images()
    assert float(dssim(a, a)) == pytest.approx(0.0, abs=1e-6)
    assert float(dssim(a, 1.0 - a)) > 1.8  # SSIM ~ -1 against the negative
    assert float(dssim(a, b)) == pytest.approx(1.0 - float(_ssim(a, b)), abs=1e-6)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_ssim_map_is_kornias_map_with_its_gradient(dtype, tol):
    # the map CUDA images take (one stacked filtering, the window made once): kornia's map and gradient
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2, 3, 20, 27, generator=g, dtype=dtype, requires_grad=True)
    b = (a.detach() + 0.2 * torch.rand(a.shape, generator=g, dtype=dtype) - 0.1).clamp(0, 1)
    ref = kornia.metrics.ssim(a, b, 11, max_val=1.0, padding="same")
    got = ssim_map(a, b)
    assert got.shape == ref.shape and (got - ref).abs().max() < tol
    ga, = torch.autograd.grad(ref.mean(), a)
    gb, = torch.autograd.grad(got.mean(), a)
    assert (ga - gb).abs().max() < tol * ga.abs().max()
    assert ssim_map(b, b).sub(1).abs().max() < 1e-6  # identical images: 1 everywhere (up to eps / den)


def test_gaussian_window_is_normalised_and_made_once():
    w = gaussian_window(11, "cpu", torch.float32)
    x = torch.arange(11, dtype=torch.float64) - 5
    expect = torch.exp(-x * x / 4.5)
    assert torch.allclose(w.double(), expect / expect.sum(), atol=1e-7) and abs(float(w.sum()) - 1) < 1e-6
    assert gaussian_window(11, torch.device("cpu"), torch.float32) is w     # cached per device and dtype
    with pytest.raises(ValueError, match="one shape"):
        ssim_map(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))


def test_photometric_loss_weights():
    a, b = _images()
    l1 = (a - b).abs().mean()
    want = 0.8 * l1 + 0.2 * (1.0 - _ssim(a, b))
    assert float(photometric(a, b)) == pytest.approx(float(want), rel=1e-6)
    assert float(photometric(a, b, 0.5)) == pytest.approx(float(0.5 * l1 + 0.5 * (1.0 - _ssim(a, b))), rel=1e-6)
    # dssim_scale=0.5: the halved term ssgwarp used before, kept for comparisons
    half = 0.8 * l1 + 0.1 * (1.0 - _ssim(a, b))
    assert float(photometric(a, b, dssim_scale=0.5)) == pytest.approx(float(half), rel=1e-6)


def test_stage2_finetune_loss_is_the_3dgs_loss():
    from ssgwarp.stylization.stage2 import finetune_loss

    a, b = _images()
    want = 0.8 * (a - b).abs().mean() + 0.2 * (1.0 - _ssim(a, b))
    assert float(finetune_loss(a[0], b[0])) == pytest.approx(float(want), rel=1e-6)


@pytest.mark.parametrize("dssim_scale", [1.0, 0.5])
def test_the_trainer_optimises_the_3dgs_loss(dssim_scale):
    """The loss of a training step is 0.8 L1 + 0.2 (1 - SSIM) of the render against the view (one training
    view, so the step's view is known); ``Recipe.dssim_scale`` 0.5 gives the old halved term."""
    V = look_at(torch.tensor([[0.0, 0.0, -3.0], [0.4, 0.0, -3.0]]), torch.zeros(2, 3), up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(20.0, 20.0, 12.0, 10.0, 2), 24, 20)
    g = torch.Generator().manual_seed(0)
    data = SceneData(cams, torch.rand(2, 20, 24, 3, generator=g), ["a", "b"], [0], [1], points=None)
    scene = GaussianScene.from_points(torch.randn(40, 3, generator=g) * 0.4, torch.rand(40, 3, generator=g),
                                      sh_degree=0, opacity=0.6)
    t = Trainer(data, scene=scene, iters=3, recipe=Recipe(sh_degree=0, dssim_scale=dssim_scale), progress=False,
                device="cpu")
    img, _, _ = render_views(t.scene.detach(), cams[0], sh_degree=0, backgrounds=data.background_tensor(3)[None])
    img = img[..., :3]
    gt = data.images[:1]
    want = 0.8 * (img - gt).abs().mean() + 0.2 * dssim_scale * (1.0 - _ssim(img, gt))
    info = t.train_step()
    assert float(info["loss"]) == pytest.approx(float(want), rel=1e-5)
