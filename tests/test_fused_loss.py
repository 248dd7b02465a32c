"""The fused photometric loss (Warp kernels, ``ssgwarp.raster.ssim_ops``) against the torch reference
``losses.photometric(..., fused=False)`` (the spec: L1 and kornia's / ``ssim_map``'s SSIM, gradients from
torch's autograd): values, gradients of both images, finite differences, sizes down to one pixel,
constant, identical and extreme images, strided inputs, several CPU threads, CUDA where present, and
which path the callers get."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import CUDA_ONLY, assert_close_elementwise
from ssgwarp.raster import ssim_ops
from ssgwarp.services import losses
from ssgwarp.services.losses import gaussian_window, photometric, ssim

TOL = {torch.float32: 1e-5, torch.float64: 1e-10}
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA_ONLY)]
# [V, H, W, C]: batches, 1, 3 and 5 channels, odd sizes, images narrower than the window (3 x 5) and one pixel
SHAPES = [(1, 24, 32, 3), (3, 17, 29, 1), (2, 20, 13, 5), (1, 3, 5, 3), (2, 6, 7, 2), (1, 1, 1, 3), (1, 1, 9, 1)]


def _pair(shape, dtype, device="cpu", seed=0, grad=True):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(shape, generator=g, dtype=torch.float64)
    b = (a + 0.3 * torch.rand(shape, generator=g, dtype=torch.float64) - 0.15).clamp(0, 1)
    a, b = a.to(device=device, dtype=dtype), b.to(device=device, dtype=dtype)
    return a.requires_grad_(grad), b


def _value_and_grads(a, b, fused, **kw):
    """The loss and its gradients with respect to every input that requires one."""
    loss = photometric(a, b, fused=fused, **kw)
    ins = [t for t in (a, b) if t.requires_grad]
    return loss.detach(), torch.autograd.grad(loss, ins) if ins else ()


def _check(a, b, name, grad_rtol=None, grad_atol=0.0, **kw):
    """The kernels' loss and gradients against the reference's: within ``TOL`` (float32: or no farther
    from the float64 reference than the float32 reference is, plus ``TOL``: tiny images average little
    of float32's rounding in the variances away; a one-pixel image's variances are that rounding alone,
    both losses then only good to ~1e-4)."""
    tol = TOL[a.dtype]
    if a.dtype == torch.float32 and tuple(a.shape[-3:-1]) == (1, 1):
        tol = 2e-4
    want, want_g = _value_and_grads(a, b, False, **kw)
    got, got_g = _value_and_grads(a, b, True, **kw)
    assert got.dtype == a.dtype and got.shape == () and got.device == a.device
    truth, truth_g = None, [None] * len(want_g)
    if a.dtype == torch.float32:
        a64, b64 = (t.detach().double().requires_grad_(t.requires_grad) for t in (a, b))
        truth, truth_g = _value_and_grads(a64, b64, False, **kw)
    err = abs(float(got) - float(want)) if truth is None else abs(float(got) - float(truth)) - abs(float(want) - float(truth))
    assert err <= tol, f"{name}: {float(got)} against {float(want)}"
    for gg, wg, tg in zip(got_g, want_g, truth_g):
        assert_close_elementwise(gg, wg, rtol=0.0, atol=(grad_rtol or tol) * float(wg.abs().max()) + grad_atol,
                                 name=f"{name} gradient", truth=tg)
    return got, got_g


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("shape", SHAPES)
def test_value_and_gradient_are_the_references(shape, dtype, device):
    a, b = _pair(shape, dtype, device)
    _check(a, b, f"{shape} {dtype}")
    b.requires_grad_(True)  # both images (SSIM and L1 are symmetric: b's gradient by the same kernels)
    _check(a, b, f"{shape} {dtype}, both")
    a.requires_grad_(False)
    _check(a, b, f"{shape} {dtype}, b only")


@pytest.mark.parametrize("lambda_dssim, dssim_scale", [(0.2, 1.0), (0.5, 0.5), (0.0, 1.0), (1.0, 1.0)])
def test_the_weights_and_an_image_without_a_view_axis(lambda_dssim, dssim_scale):
    a, b = _pair((1, 12, 15, 3), torch.float64)
    _check(a, b, "weights", lambda_dssim=lambda_dssim, dssim_scale=dssim_scale)
    _check(a[0], b[0], "[H, W, C]", lambda_dssim=lambda_dssim, dssim_scale=dssim_scale)


@pytest.mark.parametrize("shape", [(1, 7, 9, 2), (2, 3, 5, 1)])
def test_gradient_matches_finite_differences(shape):
    a, b = _pair(shape, torch.float64, seed=3)
    b.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, y: photometric(x, y, fused=True), (a, b), eps=1e-6, atol=1e-8)


def test_small_images_reflect_as_numpy_pads():
    """Images narrower than the window (torch's reflect pad refuses them) reflect again and again, as
    numpy's ``pad(mode="reflect")``: the reference and the kernels against SSIM written out in numpy."""
    from test_quality_measures import ssim_numpy

    for shape in [(3, 5, 2), (1, 4, 1), (6, 2, 3), (1, 1, 3)]:
        g = np.random.default_rng(sum(shape))
        x = g.random(shape)
        y = np.clip(0.6 * x + 0.3 * g.random(shape), 0, 1)
        want = ssim_numpy(x, y)
        X, Y = torch.from_numpy(x), torch.from_numpy(y)
        for fused in (False, True):
            assert float(ssim(X, Y, fused=fused)) == pytest.approx(want, abs=1e-8), (shape, fused)  # (numpy: no 1e-12 in den)


def test_constant_and_identical_images():
    # identical images: SSIM 1 (but for the 1e-12 in its denominator: 1 - 1.1e-5 for black images), loss 0,
    # the gradient 0 (SSIM's maximum, L1's sign 0) and finite
    for img in (torch.rand(2, 9, 11, 3, dtype=torch.float64), torch.full((1, 8, 8, 3), 0.5, dtype=torch.float64),
                torch.zeros(1, 6, 6, 1, dtype=torch.float64)):
        a = img.clone().requires_grad_(True)
        loss, (g,) = _check(a, img.clone(), "identical", grad_atol=1e-12)
        assert 0 <= float(loss) < 3e-6 and float(g.abs().max()) < 1e-10
    # constant images: SSIM = (2ab + C1) / (a^2 + b^2 + C1) per channel
    ca, cb = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64), torch.tensor([0.4, 0.5, 0.3], dtype=torch.float64)
    A, B = ca.expand(1, 10, 12, 3).clone(), cb.expand(1, 10, 12, 3).clone()
    c1 = 0.01 ** 2
    want = float(((2 * ca * cb + c1) / (ca * ca + cb * cb + c1)).mean())
    assert float(ssim(A, B, fused=True)) == pytest.approx(want, abs=1e-8)  # (the 1e-12 in the denominator)
    # the metric of float32 images is computed in float64 (float32's flat-region variances move it by ~2e-5)
    assert float(ssim(A.float(), B.float())) == pytest.approx(want, abs=1e-7)
    _check(A.requires_grad_(True), B, "constant")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_extreme_values(dtype):
    g = torch.Generator().manual_seed(5)
    ones, zeros = torch.ones(1, 10, 12, 3, dtype=dtype), torch.zeros(1, 10, 12, 3, dtype=dtype)
    binary = (torch.rand(1, 10, 12, 3, generator=g) > 0.5).to(dtype)
    for a, b, name in [(ones, zeros, "1 against 0"), (binary, 1 - binary, "a binary image against its negative"),
                       (zeros, binary, "0 against binary")]:
        loss, _ = _check(a.clone().requires_grad_(True), b, name)
        assert torch.isfinite(loss)
    # large values (outside [0, 1]): cancellation in the variances, so float32 only to its own precision
    big = torch.rand(1, 10, 12, 3, generator=g, dtype=torch.float64) * 50
    big_b = big + torch.rand(1, 10, 12, 3, generator=g, dtype=torch.float64)
    _check(big.to(dtype).requires_grad_(True), big_b.to(dtype), "large", grad_rtol=1e-10 if dtype == torch.float64
           else 2e-3)


def test_strided_inputs_read_in_place():
    """Views (a channel slice of a wider image, transposed axes, an expanded constant) give what their
    contiguous copies give, bit for bit, with no copy made by the op."""
    g = torch.Generator().manual_seed(2)
    wide = torch.rand(2, 14, 16, 4, generator=g, dtype=torch.float64)
    a = wide[..., :3]
    b = torch.rand(2, 16, 14, 3, generator=g, dtype=torch.float64).transpose(1, 2)
    assert not a.is_contiguous() and not b.is_contiguous()
    for x, y in [(a, b), (a, torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64).expand(2, 14, 16, 3))]:
        assert float(photometric(x, y, fused=True)) == float(photometric(x.contiguous(), y.contiguous(), fused=True))
        assert float(photometric(x, y, fused=True)) == pytest.approx(float(photometric(x, y, fused=False)), abs=1e-12)
    leaf = torch.rand(2, 14, 16, 4, generator=g, dtype=torch.float64, requires_grad=True)
    (ga,) = torch.autograd.grad(photometric(leaf[..., 1:], b, fused=True), leaf)
    (gc,) = torch.autograd.grad(photometric(leaf[..., 1:].contiguous(), b.contiguous(), fused=True), leaf)
    assert torch.equal(ga, gc) and float(ga[..., 0].abs().max()) == 0.0


def test_masked_pixels_as_the_trainer_zeroes_them():
    from ssgwarp.evaluation.held_out import masked as _masked

    a, b = _pair((2, 16, 18, 3), torch.float64)
    mask = torch.ones(2, 16, 18)
    mask[:, 4:9, 5:12] = 0
    la = photometric(*_masked(a, b, mask), fused=False)
    (wg,) = torch.autograd.grad(la, a)
    lf = photometric(*_masked(a, b, mask), fused=True)
    (fg,) = torch.autograd.grad(lf, a)
    assert abs(float(lf.detach()) - float(la.detach())) < 1e-12
    assert_close_elementwise(fg, wg, rtol=0.0, atol=1e-10 * float(wg.abs().max()), name="masked gradient")
    assert float(fg[:, 4:9, 5:12].abs().max()) == 0.0  # no gradient through the zeroing


def test_several_cpu_threads_give_the_same_loss_and_gradient():
    """On the CPU the kernels run over runs of pixels side by side (one per torch thread): the gradient is
    the same bits, the loss the same to the float64 sum's rounding."""
    a, b = _pair((1, 64, 96, 3), torch.float32, seed=4)
    n0 = torch.get_num_threads()
    out = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            loss = photometric(a, b, fused=True)
            out.append((loss.detach(), torch.autograd.grad(loss, a)[0]))
    finally:
        torch.set_num_threads(n0)
    for loss, g in out[1:]:
        assert abs(float(loss) - float(out[0][0])) <= 1e-7 and torch.equal(g, out[0][1])


def test_callers_get_the_fused_loss_by_default(monkeypatch):
    """photometric and ssim (evaluation) use the kernels unless told not to; without them (or for
    other dtypes) the torch reference; ``fused=True`` where they cannot run is a clear error."""
    calls = []
    real = losses.photometric_warp

    def spy(*args):
        calls.append(args[2:5])
        return real(*args)

    monkeypatch.setattr(losses, "photometric_warp", spy)
    a, b = _pair((1, 8, 9, 3), torch.float32, grad=False)
    photometric(a, b)
    photometric(a, b, 0.3, 0.5)
    ssim(a, b)
    photometric(a, b, fused=False)
    assert calls == [(0.8, -0.2, 0.2), (0.7, -0.15, 0.15), (0.0, 1.0, 0.0)]
    h = torch.rand(1, 8, 9, 3, dtype=torch.float16)
    with pytest.raises(ValueError, match="fused loss cannot run.*float16"):
        photometric(h, h, fused=True)
    monkeypatch.setattr(losses, "photometric_warp", None)
    assert float(photometric(a, b)) == pytest.approx(float(photometric(a, b, fused=False)), abs=0)
    with pytest.raises(ValueError, match="warp-lang"):
        photometric(a, b, fused=True)


def test_bad_input_is_refused():
    w = gaussian_window(11, "cpu", torch.float32)
    with pytest.raises(ValueError, match="one shape"):
        ssim_ops.photometric_warp(torch.rand(1, 8, 8, 3), torch.rand(1, 8, 9, 3), 0.8, -0.2, 0.2, w)
    with pytest.raises(ValueError, match="empty"):
        ssim_ops.photometric_warp(torch.rand(1, 0, 8, 3), torch.rand(1, 0, 8, 3), 0.8, -0.2, 0.2, w)
    with pytest.raises(ValueError, match="odd length"):
        ssim_ops.photometric_warp(torch.rand(1, 8, 8, 3), torch.rand(1, 8, 8, 3), 0.8, -0.2, 0.2, w[:10])
    # mixed precisions: promoted, as torch promotes them
    a, b = _pair((1, 8, 9, 3), torch.float64, grad=False)
    got = ssim_ops.photometric_warp(a.float(), b, 0.8, -0.2, 0.2, w)
    assert got.dtype == torch.float64


def test_the_trainer_trains_with_the_fused_loss(monkeypatch):
    """A training step's loss comes from the kernels (the trainer's default) and equals the reference."""
    from ssgwarp.core.cameras import Cameras, intrinsics, look_at
    from ssgwarp.capture.datasets import SceneData
    from ssgwarp.raster.scene import GaussianScene
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.trainer import Trainer

    calls = []
    real = losses.photometric_warp
    monkeypatch.setattr(losses, "photometric_warp", lambda *a: calls.append(a[0].shape) or real(*a))
    V = look_at(torch.tensor([[0.0, 0.0, -3.0]]), torch.zeros(1, 3), up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(20.0, 20.0, 12.0, 10.0, 1), 24, 20)
    g = torch.Generator().manual_seed(0)
    data = SceneData(cams, torch.rand(1, 20, 24, 3, generator=g), ["a"], [0], [], points=None)
    scene = GaussianScene.from_points(torch.randn(40, 3, generator=g) * 0.4, torch.rand(40, 3, generator=g),
                                      sh_degree=0, opacity=0.6)
    t = Trainer(data, scene=scene, iters=2, recipe=Recipe(sh_degree=0), progress=False, device="cpu")
    info = t.train_step()
    assert calls == [(1, 20, 24, 3)] and np.isfinite(float(info["loss"]))
