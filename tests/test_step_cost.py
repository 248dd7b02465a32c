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
from ssgwarp.reconstruction import strategy as S
from ssgwarp.reconstruction.recipe import Recipe
from ssgwarp.reconstruction import trainer as trainer_module
from ssgwarp.reconstruction.trainer import StepInfo, Trainer


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
    t = Trainer(_data(), scene=_scene(3), iters=100, sh_degree=3, recipe=Recipe(sh_interval=1000), progress=False,
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
    t = Trainer(_data(), scene=_scene(0), iters=10, sh_degree=0, progress=False, device="cpu")
    before = t.render([0])
    info = t.train_step()
    want = ((before - t.data.images[:1]) ** 2).mean()
    assert float(info["mse"]) == pytest.approx(float(want), rel=1e-6)
    empty = StepInfo(loss=torch.tensor(1.0))
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
    t = Trainer(_data(), scene=scene, iters=30, sh_degree=2, recipe=Recipe(sh_interval=2), progress=False,
                device="cpu")
    rest0 = t.params["sh_rest"].detach().clone()
    t.train_step()
    t.train_step()
    assert torch.equal(t.params["sh_rest"], rest0)
    t.train_step()
    assert not torch.equal(t.params["sh_rest"], rest0)
    for name, p in t.params.items():
        assert int(t.opt.state[p]["step"]) == 3, name
