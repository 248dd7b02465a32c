"""The training step's fixed host cost (issue 40): what a step no longer does, and that what it does
instead gives the same numbers.

* the densification statistics in one Warp kernel (``kernels/stats.py``) against the torch ops they
  replace (float32 and float64, one and several cameras, culled Gaussians, screen radii);
* a one-view step indexes no cameras, copies no image, slices and joins nothing, and makes the MSE
  only when it is read (a profile of the step's torch ops);
* below the top SH degree the higher bands still get their (zero) gradient, so Adam's step counts
  advance for every parameter as before.
"""
from __future__ import annotations

import pytest
import torch

from ssgwarp.capture.datasets import SceneData
from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.raster.rendering import _coefficients
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.reconstruction import statistics as S
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction import trainer as trainer_module
from ssgwarp.reconstruction.step import StepInfo, adam_step
from ssgwarp.reconstruction.trainer import Trainer


def _stats_case(C: int, N: int, dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    grad = torch.randn(C, N, 2, generator=g, dtype=dtype) * 1e-3
    radii = torch.randint(0, 40, (C, N, 2), generator=g, dtype=torch.int32)
    radii[:, ::5, 0] = 0  # culled on one axis: not visible
    stats = {"grad2d": torch.rand(N, generator=g, dtype=dtype), "count": torch.randint(0, 9, (N,), generator=g).to(dtype),
             "max_radii": torch.rand(N, generator=g, dtype=dtype) * 0.1}
    return grad, radii, stats


def _meta(grad, radii, width=64, height=48):
    m2d = torch.zeros_like(grad, requires_grad=True)
    m2d.grad = grad
    return {"means2d": m2d, "radii": radii, "width": width, "height": height, "n_cameras": grad.shape[0]}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("C", [1, 3])
def test_grad2d_kernel_matches_the_torch_ops(dtype, C):
    grad, radii, stats = _stats_case(C, 1000, dtype)
    warp_stats = {k: v.clone() for k, v in stats.items()}
    torch_stats = {k: v.clone() for k, v in stats.items()}
    S.accumulate_grad2d(warp_stats, _meta(grad, radii))
    # the torch ops: the same call with int64 radii (which the kernel does not take)
    S.accumulate_grad2d(torch_stats, _meta(grad, radii.long()))
    assert not torch.equal(warp_stats["grad2d"], stats["grad2d"])  # (something was added)
    assert torch.equal(warp_stats["count"], torch_stats["count"])
    rtol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(warp_stats["grad2d"], torch_stats["grad2d"], rtol=rtol, atol=0.0)
    torch.testing.assert_close(warp_stats["max_radii"], torch_stats["max_radii"], rtol=rtol, atol=0.0)
    # visible exactly where both radii are positive: the count rose by the number of such cameras
    seen = (radii > 0).all(dim=-1).sum(dim=0).to(dtype)
    assert torch.equal(warp_stats["count"], stats["count"] + seen)


def test_grad2d_kernel_without_screen_radii_and_when_it_does_not_apply():
    grad, radii, stats = _stats_case(2, 50, torch.float32, seed=1)
    del stats["max_radii"]
    a = {k: v.clone() for k, v in stats.items()}
    assert S._accumulate_warp(a, grad, radii, 64.0, 48.0, 2)
    b = {k: v.clone() for k, v in stats.items()}
    S.accumulate_grad2d(b, _meta(grad, radii.long()))
    torch.testing.assert_close(a["grad2d"], b["grad2d"], rtol=1e-6, atol=0.0)
    # what the kernel does not take is left to the torch ops (nothing done, False)
    for bad_stats, bad_grad, bad_radii in (
            ({**stats, "count": stats["count"].double()}, grad, radii),   # statistics of another dtype
            (stats, grad[0], radii[0]),                                    # packed layout
            (stats, grad, radii.long()),                                   # radii not int32
            (stats, grad.half(), radii)):                                  # half gradients
        before = {k: v.clone() for k, v in bad_stats.items()}
        assert not S._accumulate_warp(bad_stats, bad_grad, bad_radii, 64.0, 48.0, 2)
        assert all(torch.equal(before[k], bad_stats[k]) for k in before)
    # no gradient: nothing at all
    m = _meta(grad, radii)
    m["means2d"].grad = None
    c = {k: v.clone() for k, v in stats.items()}
    S.accumulate_grad2d(c, m)
    assert all(torch.equal(c[k], stats[k]) for k in stats)


def _data(views: int = 2):
    eyes = torch.tensor([[0.0, 0.0, -3.0], [0.4, 0.0, -3.0], [-0.4, 0.1, -3.0]])[:views]
    V = look_at(eyes, torch.zeros(views, 3), up=(0.0, -1.0, 0.0)).float()
    cams = Cameras(V, intrinsics(20.0, 20.0, 12.0, 10.0, views), 24, 20)
    g = torch.Generator().manual_seed(0)
    return SceneData(cams, torch.rand(views, 20, 24, 3, generator=g), [f"v{i}" for i in range(views)],
                     list(range(views - 1)), [views - 1], points=None)


def _scene(sh_degree: int):
    g = torch.Generator().manual_seed(1)
    s = GaussianScene.from_points(torch.randn(60, 3, generator=g) * 0.4, torch.rand(60, 3, generator=g),
                                  sh_degree=0, opacity=0.6)
    return s.with_sh_degree(sh_degree)


def _step_ops(trainer: Trainer) -> tuple[list[str], StepInfo]:
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as p:
        info = trainer.train_step()
    return [e.name for e in p.events()], info


def test_a_one_view_step_copies_and_joins_nothing_and_makes_no_mse(monkeypatch):
    # (the loss's own ops are another matter: an L1 loss here, so that those below are the step's)
    monkeypatch.setattr(trainer_module, "photometric", lambda a, b, *_: (a - b).abs().mean())
    t = Trainer(_data(), scene=_scene(3), iters=100, recipe=Recipe(sh_degree=3, sh_interval=1000), progress=False,
                device="cpu", seed=2)
    t.train_step()  # (Adam's state made)
    t._queue = [0, 0]  # (views queued: the step draws no new epoch, whose shuffle indexes a host tensor)
    names, info = _step_ops(t)
    for op in ("aten::index", "aten::stack", "aten::cat", "aten::slice_backward", "aten::contiguous",
               "aten::linalg_vector_norm", "aten::clamp"):
        assert op not in names, op
    # the statistics were accumulated (in the kernel) and the MSE is made when read, as before
    assert float(t.gaussians.stats["count"].sum()) > 0
    assert "mse" in info and "loss" in info and info.image_pair is not None
    mse = info["mse"]
    assert info.image_pair is None and info["mse"] is mse  # made once
    want = ((t.render([0]) - t.data.images[:1]) ** 2).mean()  # (the render after the step: close, not equal)
    assert float(mse) == pytest.approx(float(want), rel=0.2)
    assert info.get("nothing") is None and info.get("mse") is mse
    with pytest.raises(KeyError):
        info["nothing"]


def test_the_mse_is_the_clamped_render_against_its_view():
    """One training view: the step's MSE is that of the render the loss saw (the scene before the step)."""
    t = Trainer(_data(), scene=_scene(0), iters=10, recipe=Recipe(sh_degree=0), progress=False, device="cpu")
    before = t.render([0])
    info = t.train_step()
    want = ((before - t.data.images[:1]) ** 2).mean()
    assert float(info["mse"]) == pytest.approx(float(want), rel=1e-6)
    empty = StepInfo(torch.tensor(1.0))
    assert "mse" not in empty and empty.get("mse") is None


def test_lower_sh_degrees_render_a_view_of_the_dc_term_and_adam_still_steps_every_band():
    scene = _scene(2)
    c0 = _coefficients(scene, 0)
    assert c0.shape == (60, 1, 3) and c0.data_ptr() == scene.sh_dc.data_ptr() and c0.is_contiguous()
    c1 = _coefficients(scene, 1)
    assert c1.shape == (60, 4, 3) and c1.is_contiguous()
    assert torch.equal(c1, scene.sh_coeffs[:, :4]) and torch.equal(_coefficients(scene, 2), scene.sh_coeffs)
    # two steps at degree 0, then one at degree 1: every group stepped three times, the higher bands
    # unchanged while their gradient was zero
    t = Trainer(_data(), scene=scene, iters=30, recipe=Recipe(sh_degree=2, sh_interval=2), progress=False, device="cpu")
    rest0 = t.params["sh_rest"].detach().clone()
    t.train_step()
    t.train_step()
    assert torch.equal(t.params["sh_rest"], rest0)
    t.train_step()
    assert not torch.equal(t.params["sh_rest"], rest0)
    for name, p in t.params.items():
        assert int(t.opt.state[p]["step"]) == 3, name


# -- the scene's stored parameters activated in the kernels (rasterization_from_parameters) -------
F64 = torch.float64
SIZE = 12


def _stored(n: int, dtype=F64, seed: int = 0):
    """A few Gaussians in front of a camera, as a scene stores them: log-scales, logits."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * torch.tensor([0.6, 0.6, 1.0], dtype=dtype) \
        + torch.tensor([-0.3, -0.3, 3.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.log(torch.rand(n, 3, generator=g, dtype=dtype) * 0.3 + 0.2)
    logits = torch.randn(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    sh = torch.randn(n, 4, 3, generator=g, dtype=dtype) * 0.3
    sh[:, 0] += 1.0  # (colours above the clamp at 0)
    return means, quats, log_scales, logits, colors, sh


def _cams(C: int, dtype=F64):
    V = look_at(torch.tensor([[0.0, 0.0, -0.2], [0.3, 0.1, -0.3]])[:C], torch.tensor([[0.0, 0.0, 3.5]] * C),
                up=(0.0, -1.0, 0.0)).to(dtype)
    return V, intrinsics(9.0, 9.0, SIZE / 2, SIZE / 2, C, dtype=dtype)


@pytest.mark.parametrize("hand", [True, False])
@pytest.mark.parametrize("C,degree,mode", [(1, None, "classic"), (2, 1, "classic"), (1, 1, "antialiased")])
def test_activations_in_the_kernels_match_torch_activations(C, degree, mode, hand, monkeypatch):
    """float64: the images and every input's gradient through the kernels' exp / sigmoid equal those
    through torch's (the hand-written backward and Warp's generated adjoint of the forward alike)."""
    from ssgwarp import rasterization
    from ssgwarp.raster import ops
    from ssgwarp.raster.rasterize import rasterization_from_parameters

    monkeypatch.setattr(ops, "HAND_BACKWARD", hand)
    means, quats, log_scales, logits, colors, sh = _stored(25)
    vm, K = _cams(C)
    col = colors if degree is None else sh
    w = torch.rand(C, SIZE, SIZE, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    kw = dict(sh_degree=degree, rasterize_mode=mode, backgrounds=torch.rand(C, 3, dtype=F64))
    results = []
    for fused in (True, False):
        ins = [t.clone().requires_grad_(True) for t in (means, quats, log_scales, logits, col)]
        if fused:
            img, alpha, meta = rasterization_from_parameters(*ins[:4], ins[4], vm, K, SIZE, SIZE, **kw)
        else:
            img, alpha, meta = rasterization(ins[0], ins[1], ins[2].exp(), ins[3].sigmoid(), ins[4], vm, K, SIZE, SIZE,
                                             **kw)
        ((img * w).sum() + alpha.sum()).backward()
        results.append((img.detach(), meta["radii"], meta["opacities"].detach(), [t.grad for t in ins]))
    (img_a, radii_a, op_a, grads_a), (img_b, radii_b, op_b, grads_b) = results
    assert torch.equal(radii_a, radii_b) and (radii_a > 0).any()
    torch.testing.assert_close(img_a, img_b, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(op_a, op_b, rtol=1e-13, atol=0.0)
    for name, a, b in zip(["means", "quats", "log_scales", "logits", "colors"], grads_a, grads_b):
        assert b.abs().max() > 0, name
        assert ((a - b).abs().max() / b.abs().max()).item() < 1e-11, name


def test_activations_in_the_kernels_match_finite_differences():
    from ssgwarp import RasterSettings
    from ssgwarp.raster.rasterize import rasterization_from_parameters

    means, quats, log_scales, logits, _, sh = _stored(4, seed=5)
    vm, K = _cams(1)

    def f(log_scales, logits, sh):
        img, alpha, _ = rasterization_from_parameters(means, quats, log_scales, logits, sh, vm, K, SIZE, SIZE,
                                                      sh_degree=1, settings=RasterSettings.exact())
        return img, alpha

    assert torch.autograd.gradcheck(f, [t.clone().requires_grad_(True) for t in (log_scales, logits, sh)], eps=1e-6,
                                    atol=1e-6, rtol=1e-4)


def test_activations_in_the_kernels_check_what_they_make():
    """Negative log-scales and any logit are valid; a NaN is reported for the input it is in; with
    backend="torch" the activations run in torch (the same image)."""
    from ssgwarp.raster.rasterize import rasterization_from_parameters

    means, quats, log_scales, logits, colors, _ = _stored(6, seed=2)
    vm, K = _cams(1)
    assert (log_scales < 0).all() and (logits < 0).any()
    img, _, _ = rasterization_from_parameters(means, quats, log_scales, logits, colors, vm, K, SIZE, SIZE)
    ref, _, _ = rasterization_from_parameters(means, quats, log_scales, logits, colors, vm, K, SIZE, SIZE,
                                              backend="torch")
    torch.testing.assert_close(img, ref, rtol=1e-9, atol=1e-10)
    for name, bad in (("scales", log_scales.clone().index_fill_(0, torch.tensor([3]), float("nan"))),
                      ("opacities", logits.clone().index_fill_(0, torch.tensor([1]), float("nan")))):
        args = [means, quats, bad, logits] if name == "scales" else [means, quats, log_scales, bad]
        with pytest.raises(ValueError, match=name):
            rasterization_from_parameters(*args, colors, vm, K, SIZE, SIZE)


# -- Adam without its per-group Python (step.adam_step) ------------------------------------------
def _fused_groups(opt):
    from ssgwarp.core.optim import Adam
    from ssgwarp.raster.private_api import fused_adam_groups

    return fused_adam_groups(opt, (torch.optim.Adam, Adam))


def _adams():
    g = torch.Generator().manual_seed(4)
    made = []
    for _ in range(2):
        ps = [torch.nn.Parameter(torch.randn(7, k, generator=torch.Generator().manual_seed(k))) for k in (1, 3, 4)]
        groups = [{"params": [p], "lr": lr, "name": str(i)} for i, (p, lr) in enumerate(zip(ps, (1e-2, 3e-3, 1e-1)))]
        made.append((ps, torch.optim.Adam(groups, eps=1e-15, betas=(0.9, 0.99), fused=True)))
    grads = [[torch.randn(7, k, generator=g) for k in (1, 3, 4)] for _ in range(6)]
    return made, grads


def test_adam_step_is_torchs_fused_adam_to_the_bit(monkeypatch):
    ((ps_a, opt_a), (ps_b, opt_b)), grads = _adams()
    calls = []
    monkeypatch.setattr(opt_a, "step", lambda *a, **k: calls.append(1) or torch.optim.Adam.step(opt_a, *a, **k))
    for i, gs in enumerate(grads):
        for ps in (ps_a, ps_b):
            for p, gr in zip(ps, gs):
                p.grad = None if (i == 2 and p is ps[1]) else gr.clone()  # (a group without a gradient)
        skip = torch.tensor(1.0 if i == 4 else 0.0)  # (step 5: a NaN loss, the update skipped)
        opt_a.found_inf = opt_b.found_inf = skip
        adam_step(opt_a)
        opt_b.step()
        opt_b.zero_grad(set_to_none=True)
        assert all(p.grad is None for p in ps_a)
    assert calls == [1]  # torch's step made the state, the others ran here
    for pa, pb in zip(ps_a, ps_b):
        assert torch.equal(pa, pb)
        for k in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt_a.state[pa][k], opt_b.state[pb][k]), k
    assert [float(opt_a.state[p]["step"]) for p in ps_a] == [5.0, 4.0, 5.0]


def test_adam_step_leaves_what_it_does_not_mirror_to_torch():
    ((ps, opt), _), _ = _adams()
    for p in ps:
        p.grad = torch.ones_like(p)
    adam_step(opt)  # (state made)
    assert _fused_groups(opt) == []  # (no gradients: nothing to step)
    for p in ps:
        p.grad = torch.ones_like(p)
    assert [g[0]["name"] for g in _fused_groups(opt)] == ["0", "1", "2"]
    handle = opt.register_step_pre_hook(lambda *a: None)
    assert _fused_groups(opt) is None  # hooks: torch's step runs them
    handle.remove()
    opt.param_groups[0]["amsgrad"] = True
    assert _fused_groups(opt) is None
    opt.param_groups[0]["amsgrad"] = False
    unfused = torch.optim.Adam([torch.nn.Parameter(torch.zeros(3))], foreach=False)
    assert _fused_groups(unfused) is None
