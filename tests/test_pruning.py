"""Contribution-based pruning (ssgwarp/reconstruction/pruning.py): the contribution is each Gaussian's blending
weight summed over the pixels (alpha times the transmittance in front of it), checked against the alpha maps of
each Gaussian rendered alone; the schedule; the threshold and the budget; the trainer prunes with it on and
refuses it with the MCMC strategy."""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp.capture.datasets import SceneData
from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.raster.rasterize import rasterization
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.reconstruction.pruning import ContributionPruning, contributions, prune_steps
from ssgwarp.reconstruction.recipe import Recipe, resolve
from ssgwarp.reconstruction.strategy import DefaultStrategy
from ssgwarp.reconstruction.trainer import Trainer


def _cameras(views=2, w=24, h=20):
    eyes = torch.tensor([[0.0, 0.0, -3.0], [0.3, 0.1, -3.0], [-0.4, 0.1, -3.0]])[:views]
    V = look_at(eyes, torch.zeros(views, 3), up=(0.0, -1.0, 0.0)).float()
    return Cameras(V, intrinsics(20.0, 20.0, w / 2, h / 2, views), w, h)


def _params(means, scales, opacities):
    n = means.shape[0]
    return {"means": means, "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
            "log_scales": torch.log(torch.tensor(scales))[:, None].repeat(1, 3),
            "logit_opacities": torch.logit(torch.tensor(opacities))}


def _alpha(p, cams, i):
    """The alpha map of Gaussian ``i`` rendered alone ``[C, H, W]``."""
    sel = slice(i, i + 1)
    _, a, _ = rasterization(p["means"][sel], p["quats"][sel], torch.exp(p["log_scales"][sel]),
                            torch.sigmoid(p["logit_opacities"][sel]), torch.ones(1, 1), cams.viewmats, cams.Ks,
                            cams.width, cams.height)
    return a[..., 0]


def test_contribution_is_alpha_times_the_transmittance_in_front():
    # front to back: a small one off to the side, a wide half-transparent one, a smaller one behind it; a fourth
    # out of view
    means = torch.tensor([[0.5, 0.2, -1.5], [0.0, 0.0, -0.5], [0.1, 0.0, 0.5], [0.0, 0.0, -9.0]])
    p = _params(means, [0.1, 0.3, 0.15, 0.1], [0.7, 0.5, 0.9, 0.9])
    cams = _cameras()
    got = contributions(p, cams, chunk=1)
    a0, a1, a2 = (_alpha(p, cams, i) for i in range(3))
    want = [a0.sum(), (a1 * (1 - a0)).sum(), (a2 * (1 - a0) * (1 - a1)).sum()]
    for i in range(3):
        torch.testing.assert_close(got[i], want[i], rtol=1e-5, atol=1e-4)
    assert float(got[3]) == 0.0
    assert float((a0 * a1).sum()) > 0.1 and 1.0 < float(got[2]) < 0.9 * float(a2.sum())   # (partly hidden)


def test_schedule_halfway_between_resets_and_where_densification_stops():
    s = DefaultStrategy(refine_start=100, refine_stop=750, refine_every=100, reset_every=300)
    assert prune_steps(s) == {150, 450, 750}
    assert prune_steps(DefaultStrategy(refine_start=100, refine_stop=700, refine_every=100, reset_every=0)) == {400, 700}
    assert prune_steps(DefaultStrategy(refine_start=100, refine_stop=100, refine_every=100, reset_every=0)) == set()


def test_threshold_and_budget():
    pr = ContributionPruning(resolve(Recipe(sh_degree=0), DefaultStrategy(prune_contribution=1.0), 1000)[1])
    score = torch.tensor([0.5, 3.0, 1.0, 0.0, 7.0])
    assert pr.keep_mask(score).tolist() == [False, True, True, False, True]
    pr.budget = 2
    assert pr.keep_mask(score).tolist() == [False, True, False, False, True]
    assert ContributionPruning.of(resolve(Recipe(sh_degree=0), "default", 1000)[1]) is None
    assert ContributionPruning.of(resolve(Recipe(sh_degree=0), "mcmc", 1000)[1]) is None   # (no such knobs)
    with pytest.raises(InputError, match="prune_contribution"):
        ContributionPruning.of(DefaultStrategy(prune_contribution=-1.0))


def test_the_trainer_prunes_what_no_view_sees_much():
    cams = _cameras(3)
    g = torch.Generator().manual_seed(0)
    data = SceneData(cams, torch.rand(3, 20, 24, 3, generator=g), ["a", "b", "c"], [0, 1], [2], points=None)
    n = 40
    means = torch.randn(n, 3, generator=g) * 0.3
    means[:10, 2] = -40.0   # behind the cameras: seen by no view
    scene = GaussianScene.from_points(means, torch.rand(n, 3, generator=g), sh_degree=0, opacity=0.6,
                                      scale=torch.full((n,), 0.05))
    strategy = DefaultStrategy(refine_start=2, refine_stop=4, refine_every=2, reset_every=0, prune_contribution=1e-3,
                               grad_threshold=1e9, prune_opacity=0.0)   # (no densification: only this pruning changes N)
    t = Trainer(data, scene=scene, iters=6, recipe=Recipe(sh_degree=0), strategy=strategy, progress=False,
                device="cpu")
    assert t.pruning.steps == {3, 4}
    pruned = 0
    for _ in range(6):
        pruned += t.train_step().get("contribution_prune", 0)
    assert 10 <= pruned < n and t.num_gaussians == n - pruned
    assert all(v.shape[0] == t.num_gaussians for v in t.params.values())
    assert all(st["exp_avg"].shape[0] == t.num_gaussians for st in t.opt.state.values())
    assert not math.isnan(float(t.train_step()["loss"]))
