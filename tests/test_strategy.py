"""Densification strategies: row surgery keeps every per-Gaussian tensor and its Adam state in step,
the gradient statistics match hand-derived values, the 3DGS rules clone / split / prune as stated, the
MCMC relocation formula, budget and noise, and a schedule that scales with the run's length."""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.reconstruction.recipe import Recipe, resolve
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.reconstruction.gaussians import GaussianParams
from ssgwarp.reconstruction.strategy import REFERENCE_ITERS, REFINE_EPOCHS, STRATEGIES, DefaultStrategy, MCMCStrategy, Schedule, make_strategy, relocation, scaled_schedule
from ssgwarp.reconstruction.statistics import accumulate_grad2d
from ssgwarp.errors import InputError

NAMES = ("means", "log_scales", "quats", "logit_opacities", "sh_dc", "sh_rest", "identities")


def _scene(n=12, seed=1) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    s = GaussianScene.from_points(torch.randn(n, 3, generator=g) * 0.3, torch.rand(n, 3, generator=g), sh_degree=1,
                                  opacity=0.5, scale=torch.full((n,), 0.001))
    return s.replace(sh_rest=torch.randn(n, 3, 3, generator=g), identities=torch.randn(n, 5, generator=g),
                     logit_opacities=torch.randn(n, generator=g))


def _gaussians(scene: GaussianScene, stepped: bool = True) -> GaussianParams:
    """Parameters of ``scene`` with Adam (one named group per tensor), after one step when ``stepped``
    so that every tensor has non-zero moments."""
    params = {k: torch.nn.Parameter(v.detach().clone()) for k, v in scene.tensors().items()}
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-2, "name": k} for k, p in params.items()], eps=1e-15)
    if stepped:
        g = torch.Generator().manual_seed(7)
        loss = sum((p * torch.randn(p.shape, generator=g)).sum() + (p ** 2).sum() for p in params.values())
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
    return GaussianParams(params, opt)


def _moments(g: GaussianParams, name: str) -> dict[str, torch.Tensor]:
    st = g.opt.state[g.params[name]]
    return {"exp_avg": st["exp_avg"].clone(), "exp_avg_sq": st["exp_avg_sq"].clone()}


def _snapshot(g: GaussianParams):
    return ({k: v.detach().clone() for k, v in g.params.items()}, {k: _moments(g, k) for k in g.params},
            {k: v.clone() for k, v in g.stats.items()})


def _check_consistent(g: GaussianParams) -> None:
    """Every parameter, its moments and every statistic have N rows; the optimizer holds exactly these params."""
    n = len(g)
    held = [grp["params"][0] for grp in g.opt.param_groups]
    assert len(held) == len(g.params) and all(any(h is p for h in held) for p in g.params.values())
    for k, p in g.params.items():
        assert p.shape[0] == n, k
        for m in _moments(g, k).values():
            assert m.shape == p.shape, k
    for k, v in g.stats.items():
        assert v.shape[0] == n, k
    assert set(g.opt.state) <= set(g.params.values())


def test_row_surgery_moves_every_tensor_and_its_adam_state():
    g = _gaussians(_scene())
    g.stats = {"grad2d": torch.arange(12.0), "count": torch.arange(12.0) + 100}
    p0, m0, s0 = _snapshot(g)
    assert set(p0) == set(NAMES)

    # keep: rows (and their moments and statistics) move together, in order
    mask = torch.tensor([i % 3 != 1 for i in range(12)])
    g.keep(mask)
    _check_consistent(g)
    assert len(g) == 8
    for k in NAMES:
        assert torch.equal(g.params[k].detach(), p0[k][mask]), k
        for mk, mv in _moments(g, k).items():
            assert torch.equal(mv, m0[k][mk][mask]), (k, mk)
    assert torch.equal(g.stats["grad2d"], s0["grad2d"][mask])

    # append: new rows at the end with zero moments and statistics; old rows untouched
    p1, m1, _ = _snapshot(g)
    rows = {k: torch.full((3,) + tuple(v.shape[1:]), 7.0) for k, v in g.params.items()}
    g.append(rows)
    _check_consistent(g)
    assert len(g) == 11
    for k in NAMES:
        assert torch.equal(g.params[k].detach()[:8], p1[k]) and bool((g.params[k].detach()[8:] == 7.0).all()), k
        for mk, mv in _moments(g, k).items():
            assert torch.equal(mv[:8], m1[k][mk]) and float(mv[8:].abs().sum()) == 0.0, (k, mk)
    assert float(g.stats["count"][8:].abs().sum()) == 0.0 and torch.equal(g.stats["count"][:8], s0["count"][mask])
    with pytest.raises(ValueError, match="no rows for"):
        g.append({"means": torch.zeros(1, 3)})

    # assign: in place; the named tensors get the values, every tensor's moments of those rows are zeroed
    p2, m2, _ = _snapshot(g)
    objs = {k: v for k, v in g.params.items()}
    idx = torch.tensor([1, 4])
    g.assign(idx, {"logit_opacities": torch.tensor([-1.0, 2.0]), "means": torch.zeros(2, 3)})
    _check_consistent(g)
    assert all(g.params[k] is objs[k] for k in NAMES)
    other = torch.tensor([i not in (1, 4) for i in range(11)])
    assert torch.equal(g.params["logit_opacities"].detach()[idx], torch.tensor([-1.0, 2.0]))
    assert torch.equal(g.params["sh_rest"].detach(), p2["sh_rest"])  # not named: values kept
    for k in NAMES:
        assert torch.equal(g.params[k].detach()[other], p2[k][other]), k
        for mk, mv in _moments(g, k).items():
            assert float(mv[idx].abs().sum()) == 0.0 and torch.equal(mv[other], m2[k][mk][other]), (k, mk)
    assert float(g.stats["grad2d"][idx].abs().sum()) == 0.0

    # the optimizer still steps on the edited tensors
    sum((p ** 2).sum() for p in g.params.values()).backward()
    g.opt.step()
    _check_consistent(g)


def _setup(strategy, scene, *, iters=1000, max_gaussians=1000, extent=1.0, stepped=True, **knobs):
    g = _gaussians(scene, stepped=stepped)
    r, s = resolve(Recipe(sh_degree=1), STRATEGIES[strategy](max_gaussians=max_gaussians, **knobs), iters)
    s.setup(g, recipe=r, extent=extent, seed=0)
    return g, s


def _resolved(iters, strategy="default", recipe=None, **kw):
    """The resolved strategy of a run (its recipe as ``.recipe``)."""
    r, s = resolve(recipe or Recipe(), strategy, iters, **kw)
    s.recipe = r
    return s


def _refine_scene() -> GaussianScene:
    s = _scene()
    ls = s.log_scales.clone()
    ls[4:8] = math.log(0.5)   # large: split
    lo = torch.zeros(12)
    lo[8] = -8.0              # nearly transparent: pruned
    return s.replace(log_scales=ls, logit_opacities=lo)


def test_default_refine_clones_splits_and_prunes_every_tensor_with_its_state():
    g, s = _setup("default", _refine_scene(), iters=REFERENCE_ITERS)
    g.stats["grad2d"][0:8] = 1.0
    g.stats["count"][:] = 1.0
    before, mom, _ = _snapshot(g)
    info = s.refine(g, step=200)  # before the first opacity reset: no size pruning
    assert info == {"clone": 4, "split": 4, "prune": 1}
    _check_consistent(g)
    assert len(g) == 12 + 4 + 4 - 1
    keep = [0, 1, 2, 3, 9, 10, 11]  # survivors first (minus the split and pruned ones), then clones, then children
    for k in NAMES:
        v = g.params[k].detach()
        assert torch.equal(v[:7], before[k][keep]), k
        if k != "logit_opacities":  # (the pruned one is not among the clones)
            assert torch.equal(v[7:11], before[k][0:4]), k       # clones: exact copies
        if k not in ("means", "log_scales"):
            assert torch.equal(v[11:], before[k][4:8].repeat((2,) + (1,) * (v.ndim - 1))), k
        for mk, mv in _moments(g, k).items():
            assert torch.equal(mv[:7], mom[k][mk][keep]), (k, mk)  # survivors keep their moments
            assert float(mv[7:].abs().sum()) == 0.0, (k, mk)       # new Gaussians start at zero
    assert torch.allclose(g.params["log_scales"][11:], (before["log_scales"][4:8] - math.log(1.6)).repeat(2, 1))
    d = (g.params["means"][11:] - before["means"][4:8].repeat(2, 1)).detach().norm(dim=1)
    assert bool((d > 0).all()) and bool((d < 0.5 * 6).all())   # sampled from the parent (sigma 0.5)
    assert all(float(v.abs().sum()) == 0.0 for v in g.stats.values())  # statistics restart

    # the cap: only the highest-gradient candidates grow
    g2, s2 = _setup("default", _refine_scene(), max_gaussians=14)
    g2.stats["grad2d"][0:8] = torch.arange(1.0, 9.0)
    g2.stats["count"][:] = 1.0
    info = s2.refine(g2, step=200)
    assert info == {"clone": 0, "split": 2, "prune": 1} and len(g2) == 13  # 6 and 7 have the top gradients

    # opacity reset: capped at 0.01, the opacities' moments cleared, other moments kept
    mom = _snapshot(g)[1]
    s.reset_opacities(g)
    assert float(torch.sigmoid(g.params["logit_opacities"].detach()).max()) <= 0.01 + 1e-6
    assert float(_moments(g, "logit_opacities")["exp_avg"].abs().sum()) == 0.0
    assert torch.equal(_moments(g, "means")["exp_avg"], mom["means"]["exp_avg"])


def test_size_pruning_in_world_and_on_screen_after_the_first_reset():
    sc = _scene(6).replace(logit_opacities=torch.zeros(6), log_scales=torch.full((6, 3), math.log(0.01)))
    ls = sc.log_scales.clone()
    ls[1, 2] = math.log(0.2)  # largest axis 0.2 > 0.1 x extent 1.5 = 0.15: too large in the world
    sc = sc.replace(log_scales=ls)
    g, s = _setup("default", sc, iters=REFERENCE_ITERS, extent=1.5, prune_screen=0.15)
    assert s.schedule.reset_every == 3000 and "max_radii" in g.stats
    g.stats["max_radii"][3] = 0.2   # a fifth of the larger image side: too large on screen
    g.stats["max_radii"][4] = 0.1
    assert s.refine(g, step=2000)["prune"] == 0  # before the first reset: no size pruning
    g.stats["max_radii"][3] = 0.2
    g.stats["max_radii"][4] = 0.1
    ids = g.params["identities"].detach().clone()
    assert s.refine(g, step=3100)["prune"] == 2
    assert torch.equal(g.params["identities"].detach(), ids[[0, 2, 4, 5]])
    # screen pruning off (the default): no radii kept, only the world rule
    g, s = _setup("default", sc, iters=REFERENCE_ITERS, extent=1.5)
    assert "max_radii" not in g.stats and s.refine(g, step=3100)["prune"] == 1


def _two_views(w=8, h=6):
    V = look_at(torch.tensor([[0.0, 0.0, -3.0], [3.0, 0.0, 0.0]]), torch.zeros(2, 3), up=(0.0, -1.0, 0.0)).float()
    return Cameras(V, intrinsics(8.0, 8.0, w / 2, h / 2, 2), w, h)


def test_gradient_statistics_by_hand():
    """Three Gaussians, two 8x6 views: A at the origin (seen by both), B just in front of view 0 and
    outside view 1, C behind view 0 and outside view 1. A loss linear in means2d fixes its gradient."""
    from ssgwarp.raster.rasterize import rasterization

    cams = _two_views()
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -2.5], [0.0, 0.0, -5.0]], requires_grad=True)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(3, 1)
    _, _, meta = rasterization(means, quats, torch.full((3, 3), 0.01), torch.full((3,), 0.5), torch.rand(3, 3),
                               cams.viewmats, cams.Ks, 8, 6)
    vis = (meta["radii"] > 0).all(dim=-1)
    assert vis.tolist() == [[True, True, False], [True, False, False]]
    meta["means2d"].retain_grad()
    k = 1e-3
    # pixel gradients (3k / 8, 4k / 6) per unit: NDC x (W/2 x C, H/2 x C) = (8, 6) -> (3k, 4k), norm 5k
    unit = torch.tensor([3 * k / 8, 4 * k / 6])
    weight = torch.stack([unit * torch.tensor([[1.0], [2.0], [9.0]]), unit * torch.tensor([[3.0], [9.0], [9.0]])])
    (meta["means2d"] * weight).sum().backward()
    stats = {"grad2d": torch.zeros(3), "count": torch.zeros(3), "max_radii": torch.zeros(3)}
    accumulate_grad2d(stats, meta)
    assert stats["count"].tolist() == [2.0, 1.0, 0.0]
    assert torch.allclose(stats["grad2d"], torch.tensor([5 * k * (1 + 3), 5 * k * 2, 0.0]), rtol=1e-5)
    r = meta["radii"].max(dim=-1).values.float()
    assert torch.allclose(stats["max_radii"], torch.stack([torch.max(r[0, 0], r[1, 0]), r[0, 1], r[0, 2] * 0]) / 8)
    # a second render adds up
    accumulate_grad2d(stats, meta)
    assert stats["count"].tolist() == [4.0, 2.0, 0.0]

    # packed layout (one row per visible (camera, Gaussian)): the same statistics
    c, i = torch.nonzero(vis, as_tuple=True)
    m2 = meta["means2d"].detach()[c, i].requires_grad_(True)
    (m2 * weight[c, i]).sum().backward()
    packed = {"means2d": m2, "radii": meta["radii"][c, i], "gaussian_ids": i, "width": 8, "height": 6,
              "n_cameras": 2}
    st2 = {"grad2d": torch.zeros(3), "count": torch.zeros(3), "max_radii": torch.zeros(3)}
    accumulate_grad2d(st2, packed)
    accumulate_grad2d(st2, packed)
    for key in stats:
        assert torch.allclose(st2[key], stats[key]), key


def _double_sum(o: float, n: int) -> tuple[float, float]:
    """The paper's eq. 9 as written: new opacity and the scale factor o / D."""
    q = 1.0 - (1.0 - o) ** (1.0 / n)
    d = sum(math.comb(i - 1, k) * (-1) ** k * q ** (k + 1) / math.sqrt(k + 1)
            for i in range(1, n + 1) for k in range(i))
    return q, o / d


def test_relocation_formula():
    # hand case: o = 0.75 split in two -> o' = 1 - sqrt(0.25) = 0.5, D = 2 o' - o'^2 / sqrt(2)
    o_new, s_new = relocation(torch.tensor([0.75]), torch.tensor([[1.0, 2.0, 4.0]]), torch.tensor([2]))
    d = 2 * 0.5 - 0.25 / math.sqrt(2)
    assert math.isclose(float(o_new), 0.5, rel_tol=1e-6)
    assert torch.allclose(s_new, torch.tensor([[1.0, 2.0, 4.0]]) * 0.75 / d, rtol=1e-6)
    # n = 1: unchanged; the double sum of the paper for n up to 10
    o_new, s_new = relocation(torch.tensor([0.3]), torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([1]))
    assert math.isclose(float(o_new), 0.3, rel_tol=1e-6) and torch.allclose(s_new, torch.full((1, 3), 0.5))
    os_ = torch.tensor([0.01, 0.2, 0.5, 0.9, 0.999], dtype=torch.float64)
    for n in range(1, 11):
        o_new, s_new = relocation(os_, torch.ones(5, 3, dtype=torch.float64), torch.full((5,), n))
        for j, o in enumerate(os_.tolist()):
            q, c = _double_sum(o, n)
            assert math.isclose(float(o_new[j]), q, rel_tol=1e-10) and math.isclose(float(s_new[j, 0]), c, rel_tol=1e-9)
    # n copies composite back to the original opacity; stable where the alternating sum is not
    o_new, s_new = relocation(torch.tensor([0.99, 1.0]), torch.ones(2, 3), torch.tensor([500, 5000]))
    assert torch.allclose(1 - (1 - o_new.double()) ** torch.tensor([500.0, 5000.0], dtype=torch.float64),
                          torch.tensor([0.99, 1.0], dtype=torch.float64), atol=1e-5)
    assert bool(torch.isfinite(s_new).all()) and bool((s_new > 0).all()) and bool((s_new < 1).all())


def _mcmc_scene() -> GaussianScene:
    s = _scene()
    lo = torch.full((12,), 1.0)
    lo[[2, 5, 9]] = -7.0   # dead: opacity ~0.0009 <= 0.005
    lo[0] = 3.0
    return s.replace(logit_opacities=lo, log_scales=torch.randn(12, 3, generator=torch.Generator().manual_seed(3)) - 3)


def test_mcmc_relocation_moves_dead_gaussians_onto_live_ones():
    g, s = _setup("mcmc", _mcmc_scene(), max_gaussians=14)
    assert isinstance(s, MCMCStrategy) and s.schedule.reset_every == 0
    before, mom, _ = _snapshot(g)
    gen_state = s.generator.get_state()
    assert s.relocate(g) == 3
    _check_consistent(g)
    assert len(g) == 12  # the count is kept
    # the sources drawn (same generator state): live Gaussians, by opacity
    s.generator.set_state(gen_state)
    opac0 = torch.sigmoid(before["logit_opacities"])
    alive = torch.tensor([i for i in range(12) if i not in (2, 5, 9)])
    src = alive[torch.multinomial(opac0[alive], 3, replacement=True, generator=s.generator)]
    n = torch.bincount(src, minlength=12)[src] + 1
    o_new, s_new = relocation(opac0[src], torch.exp(before["log_scales"][src]), n)
    dead = torch.tensor([2, 5, 9])
    for k in NAMES:
        v = g.params[k].detach()
        if k == "logit_opacities":
            assert torch.allclose(torch.sigmoid(v[src]), o_new, atol=1e-6)
        elif k == "log_scales":
            assert torch.allclose(v[src], torch.log(s_new), atol=1e-6)
        else:
            assert torch.equal(v[dead], before[k][src]), k   # the dead take everything else from their source
        assert torch.equal(v[dead], v[src]), k
        untouched = torch.tensor([i not in set(src.tolist()) | {2, 5, 9} for i in range(12)])
        assert torch.equal(v[untouched], before[k][untouched]), k
        for mk, mv in _moments(g, k).items():
            assert float(mv[dead].abs().sum()) == 0.0 and float(mv[src].abs().sum()) == 0.0, (k, mk)
            assert torch.equal(mv[untouched], mom[k][mk][untouched]), (k, mk)

    # growth: ceil(5%) per refinement, never past the budget
    assert s.add(g) == 1 and len(g) == 13
    _check_consistent(g)
    assert s.add(g) == 1 and s.add(g) == 0 and len(g) == 14
    new = g.params["identities"].detach()[12:]
    assert all(any(torch.equal(r, q) for q in g.params["identities"].detach()[:12]) for r in new)  # copies
    assert float(_moments(g, "sh_rest")["exp_avg"][12:].abs().sum()) == 0.0


def test_mcmc_noise_is_gated_by_opacity_and_scaled_by_covariance_and_lr():
    sc = _scene(4).replace(logit_opacities=torch.tensor([-8.0, torch.logit(torch.tensor(0.005)).item(), 0.0, 4.0]),
                           log_scales=torch.log(torch.tensor([[0.2, 0.2, 0.2]] * 4)),
                           quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 4))
    g, s = _setup("mcmc", sc, extent=2.0, stepped=False)
    m0 = g.params["means"].detach().clone()
    state = s.generator.get_state()
    s.perturb(g, lr_means=1e-4)
    s.generator.set_state(state)
    z = torch.randn(4, 3, generator=s.generator)
    o = torch.sigmoid(sc.logit_opacities)
    gate = torch.sigmoid(-100 * (o - 0.005))
    # isotropic: Sigma z = (0.2 / extent)^2 z
    expected = 5e5 * 1e-4 * gate[:, None] * (0.2 / 2.0) ** 2 * z
    assert torch.allclose(g.params["means"].detach() - m0, expected, atol=1e-7)
    assert math.isclose(float(gate[1]), 0.5, rel_tol=1e-4) and float(gate[3]) < 1e-40
    # the regulariser: mean opacity and mean scale / extent, weights 0.01
    reg = s.regularizer(g).detach()
    assert math.isclose(float(reg), 0.01 * float(o.mean()) + 0.01 * 0.2 / 2.0, rel_tol=1e-5)


def test_schedule_scales_with_the_run_length():
    ref = scaled_schedule(REFERENCE_ITERS, **DefaultStrategy.reference)
    assert ref == {"refine_start": 500, "refine_stop": 15000, "refine_every": 100, "reset_every": 3000}
    assert scaled_schedule(7000, **DefaultStrategy.reference) == {
        "refine_start": 117, "refine_stop": 3500, "refine_every": 100, "reset_every": 700}
    short = _resolved(500, "default")
    assert (short.refine_start, short.refine_stop, short.refine_every, short.reset_every) == (100, 250, 100, 300)
    sched = Schedule(short.refine_start, short.refine_stop, short.refine_every, short.reset_every)
    assert [t for t in range(501) if sched.refines_at(t)] == [100, 200]
    assert not any(sched.resets_at(t) for t in range(501))  # a reset needs 300 steps to recover: none here
    mc = _resolved(500, "mcmc")
    assert (mc.refine_start, mc.refine_stop, mc.refine_every) == (100, 417, 100) and "reset_every" not in mc.knobs()
    assert (mc.recipe.init_opacity, mc.recipe.init_scale, mc.opacity_reg, mc.scale_reg) == (0.5, 0.1, 0.01, 0.01)
    # the default strategy starts as 3DGS does (no regulariser); a dense random cloud with narrower Gaussians
    assert (short.recipe.init_opacity, short.recipe.init_scale) == (0.1, 1.0)
    assert "opacity_reg" not in DefaultStrategy.knobs() and "grad_threshold" not in MCMCStrategy.knobs()
    rnd = _resolved(500, "default", random_init=100_000).recipe
    assert rnd.init_opacity == 0.1 and math.isclose(rnd.init_scale, 0.02 ** (1 / 6))
    assert _resolved(500, "default", random_init=2000).recipe.init_scale == 1.0   # sparse: the 3DGS start
    assert _resolved(500, "default", Recipe(init_scale=2.0), random_init=100_000).recipe.init_scale == 2.0
    assert _resolved(500, "mcmc", random_init=100_000).recipe.init_scale == 0.1
    long = _resolved(60000)  # longer runs stretch every interval
    assert (long.refine_start, long.refine_stop, long.refine_every, long.reset_every) == (1000, 30000, 200, 6000)
    given = DefaultStrategy(refine_start=3, refine_every=7)
    kept = _resolved(500, given)  # given values are kept (the given strategy is left as it is)
    assert (kept.refine_start, kept.refine_every, kept.refine_stop) == (3, 7, 250) and given.refine_stop is None
    with pytest.raises(InputError, match="refine_every"):
        _resolved(100, DefaultStrategy(refine_every=0))
    with pytest.raises(InputError, match="sh_degree must be 0..3"):
        _resolved(100, recipe=Recipe(sh_degree=4))
    with pytest.raises(InputError, match="unknown strategy 'nope'"):
        make_strategy("nope")


def test_sparse_captures_stop_densifying_after_200_passes_over_their_views():
    """Densification ends once every training view was seen REFINE_EPOCHS (200) times, when that comes first:
    fern's 17 views at 30k steps refine until 3,400 (not 15,000); 88 views keep the scaled 15,000; a given
    refine_stop is kept; batches count images."""
    assert REFINE_EPOCHS == 200
    assert _resolved(30000, views=17).refine_stop == 3400
    assert _resolved(30000, views=88).refine_stop == 15000
    assert _resolved(7000, views=17).refine_stop == 3400        # (3,500 scaled)
    assert _resolved(30000).refine_stop == 15000                 # views unknown: the scaled schedule
    assert _resolved(30000, DefaultStrategy(refine_stop=9000), views=17).refine_stop == 9000
    assert _resolved(30000, "mcmc", views=17).refine_stop == 3400
    assert _resolved(15000, views=17, batch_size=2).refine_stop == 1700   # 3,400 images in steps of 2
    tiny = _resolved(30000, views=1)            # never before one refinement
    assert tiny.refine_stop == tiny.refine_start + tiny.refine_every + 1


def test_far_field_measures_sizes_against_the_distance_beyond_the_scene_radius():
    """With a far field (a backdrop) a Gaussian beyond the scene radius is measured against extent x distance /
    scene radius: a far one 0.5 wide at distance 20 (scene radius 2, extent 1: reference 10) is small enough to be
    cloned and is not pruned as too large; without the far field it is split and pruned."""
    n = 4
    means = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [20.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    sc = _scene(n).replace(means=means, logit_opacities=torch.zeros(n), log_scales=torch.full((n, 3), math.log(0.005)))
    ls = sc.log_scales.clone()
    ls[2] = math.log(0.05)     # far: 0.05 <= 0.01 x 10 (clone), > 0.01 x extent (split without the far field)
    ls[3, 0] = math.log(0.5)   # near and too large anywhere: 0.5 > 0.1 x extent
    sc = sc.replace(log_scales=ls)
    for far in (True, False):
        g, s = _setup("default", sc, iters=REFERENCE_ITERS, extent=1.0)
        if far:
            s.far_field(torch.zeros(3), 2.0)
            assert torch.allclose(s.size_reference(g.params["means"].data), torch.tensor([1.0, 1.0, 10.0, 1.0]), atol=0.01)
        else:
            assert s.size_reference(g.params["means"].data) == 1.0
        g.stats["grad2d"][2] = 1.0   # only the far one is densified (before the first reset: no size pruning)
        g.stats["count"][:] = 1.0
        info = s.refine(g, step=2000)
        assert (info["clone"], info["split"]) == ((1, 0) if far else (0, 1)), far
    # world-size pruning: 0.9 wide at distance 20 passes with the far field (0.1 x 10 = 1), not without
    ls2 = sc.log_scales.clone()
    ls2[2] = math.log(0.9)
    for far, pruned in ((True, 1), (False, 2)):
        g, s = _setup("default", sc.replace(log_scales=ls2), iters=REFERENCE_ITERS, extent=1.0)
        if far:
            s.far_field(torch.zeros(3), 2.0)
        assert s.refine(g, step=3100)["prune"] == pruned


def test_a_resume_record_with_the_flat_recipe_of_earlier_versions_reads_as_todays():
    """upgrade_record: the flat ``recipe`` of earlier resume records (both strategies' knobs in it) becomes
    today's ``recipe`` + ``strategy``: the record's strategy's knobs (mcmc_growth is growth; a None the run
    resolved to the strategy's value is that value), the other strategy's dropped; today's records as they are."""
    from dataclasses import asdict

    from ssgwarp.reconstruction.recipe import options_record, upgrade_record

    flat = {**{k: v for k, v in asdict(Recipe()).items() if k not in ("sh_degree", "res_start", "batch_scaling")},
            "refine_start": None, "refine_stop": None, "refine_every": 50, "reset_every": None,
            "grad_threshold": 0.0003, "percent_dense": 0.01, "split_factor": 1.6, "prune_opacity": 0.005,
            "reset_opacity": 0.01, "prune_world": 0.1, "prune_screen": 0.0, "mcmc_growth": 0.1, "noise_lr": 5e5,
            "opacity_reg": None, "scale_reg": None}
    old = {"--sh-degree": 3, "--max-gaussians": 1_000_000, "--coarse-to-fine": 1.0, "--batch-scaling": "sqrt",
           "--seed": 0, "recipe": flat}
    for name, strategy in (("default", DefaultStrategy(refine_every=50, grad_threshold=0.0003)),
                           ("mcmc", MCMCStrategy(refine_every=50, growth=0.1))):
        now = options_record(Recipe(), strategy)
        up = upgrade_record({**old, "--strategy": name})
        assert up == {**now, "--seed": 0}, name
        assert upgrade_record(up) == up and upgrade_record(None) is None
    assert upgrade_record({**old, "--strategy": "mcmc"})["strategy"]["opacity_reg"] == 0.01
