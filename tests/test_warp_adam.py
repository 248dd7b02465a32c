"""WarpAdam (ssgwarp/raster/adam_ops.py, kernels/adam.py): one Warp launch over every parameter group does
torch.optim.Adam's update (float32, many steps, per-group learning rates and weight decay), through
densification's row surgery, state dicts both ways and a skipped (NaN) step; the trainer selects it with
``Recipe(optimizer="warp")``."""
from __future__ import annotations

import copy

import pytest
import torch

from conftest import CUDA_ONLY
from ssgwarp.core.optim import Adam
from ssgwarp.raster import adam_ops
from ssgwarp.raster.adam_ops import WarpAdam, warp_adam
from ssgwarp.reconstruction.recipe import Recipe, resolve
from ssgwarp.reconstruction.gaussians import GaussianParams
from ssgwarp.errors import InputError
from ssgwarp.reconstruction.trainer import Trainer
from test_step_cost import _data, _scene   # (the small capture and scene the step tests train on)

SHAPES = {"means": (40, 3), "quats": (40, 4), "logit_opacities": (40,), "sh_dc": (40, 1, 3), "sh_rest": (40, 3, 3)}
LRS = {"means": 1e-2, "quats": 1e-3, "logit_opacities": 5e-2, "sh_dc": 2.5e-3, "sh_rest": 1e-4}
TOL = dict(rtol=1e-5, atol=2e-6)


def _params(seed=1):
    g = torch.Generator().manual_seed(seed)
    return {k: torch.nn.Parameter(torch.randn(s, generator=g)) for k, s in SHAPES.items()}


def _groups(params, decay=False):
    return [{"params": [p], "lr": LRS[k], "name": k, **({"weight_decay": 0.01} if decay and k == "quats" else {})}
            for k, p in params.items()]


def _grads(params, g):
    """Gradients that depend on the parameters (a quadratic pull) plus noise, as training's do."""
    return {k: torch.randn(p.shape, generator=g) * 0.1 + 0.5 * p.detach() for k, p in params.items()}


def _pair(decay=False, torch_kwargs=None):
    pa, pb = _params(), _params()
    oa = torch.optim.Adam(_groups(pa, decay), eps=1e-15, betas=(0.9, 0.999), **(torch_kwargs or {"foreach": False}))
    ob = WarpAdam(_groups(pb, decay), eps=1e-15, betas=(0.9, 0.999))
    return GaussianParams(pa, oa), GaussianParams(pb, ob)


def _step_both(a: GaussianParams, b: GaussianParams, g: torch.Generator, skip=()):
    for k, gr in _grads(a.params, g).items():
        if k in skip:
            continue
        a.params[k].grad, b.params[k].grad = gr.clone(), gr.clone()
    a.opt.step()
    b.opt.step()
    for x in (a, b):
        x.opt.zero_grad(set_to_none=True)


def _assert_same(a: GaussianParams, b: GaussianParams):
    for k in a.params:
        torch.testing.assert_close(b.params[k].detach(), a.params[k].detach(), **TOL, msg=k)
        sa, sb = a.opt.state[a.params[k]], b.opt.state[b.params[k]]
        for m in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(sb[m], sa[m], **TOL, msg=f"{k} {m}")
        assert float(sb["step"]) == float(sa["step"]), k


@pytest.mark.parametrize("decay, chunk", [(False, adam_ops.CPU_CHUNK), (True, 7)])
def test_one_launch_is_torchs_adam_over_many_steps(decay, chunk, monkeypatch):
    """(``chunk``: elements per CPU thread; 7 splits every group into chunks, the last one short.)"""
    monkeypatch.setattr(adam_ops, "CPU_CHUNK", chunk)
    launches = []
    real = adam_ops.L.launch
    monkeypatch.setattr(adam_ops.L, "launch", lambda *a, **k: (launches.append(1), real(*a, **k)))
    a, b = _pair(decay)
    g = torch.Generator().manual_seed(2)
    for i in range(150):
        # a group without a gradient (sh_rest at SH degree 0 in early steps) is left alone, as torch does
        _step_both(a, b, g, skip=("sh_rest",) if i < 5 else ())
    _assert_same(a, b)
    assert len(launches) == 150   # every group in one launch per step
    assert float(b.opt.state[b.params["sh_rest"]]["step"]) == 145


def test_row_surgery_between_steps_keeps_matching_torch():
    """Densification's edits (prune, clone / split rows appended with zero moments, relocation's rewritten
    rows, an opacity reset's zeroed moments) between steps: both optimisers go on identically."""
    a, b = _pair()
    g = torch.Generator().manual_seed(3)
    for _ in range(20):
        _step_both(a, b, g)
    keep = torch.arange(40) % 5 != 2
    for x in (a, b):
        x.keep(keep)
    for _ in range(15):
        _step_both(a, b, g)
    rows = {k: torch.full((6,) + tuple(p.shape[1:]), 0.3) for k, p in a.params.items()}
    for x in (a, b):
        x.append(rows)
        x.assign(torch.tensor([0, 3, 7]), {"logit_opacities": torch.tensor([-1.0, 0.5, 2.0])})
    for _ in range(15):
        _step_both(a, b, g)
    for x in (a, b):
        x.zero_moments("logit_opacities")
    for _ in range(20):
        _step_both(a, b, g)
    assert len(b) == 32 + 6
    _assert_same(a, b)


def test_state_dicts_go_both_ways_with_torchs_adam():
    """A WarpAdam state dict resumes in torch's Adam and torch's (fused) in WarpAdam; the runs go on as one."""
    a, b = _pair(torch_kwargs={"fused": True})
    g = torch.Generator().manual_seed(4)
    for _ in range(25):
        _step_both(a, b, g)
    sa, sb = copy.deepcopy(a.opt.state_dict()), copy.deepcopy(b.opt.state_dict())   # (as a checkpoint file holds)
    # swap: torch's state into a fresh WarpAdam, WarpAdam's into a fresh torch Adam
    pa2 = {k: torch.nn.Parameter(v.detach().clone()) for k, v in b.params.items()}
    pb2 = {k: torch.nn.Parameter(v.detach().clone()) for k, v in a.params.items()}
    oa2 = torch.optim.Adam(_groups(pa2), eps=1e-15)
    oa2.load_state_dict(sb)
    ob2 = WarpAdam(_groups(pb2), eps=1e-15)
    ob2.load_state_dict(sa)
    assert all(not grp["fused"] for grp in ob2.param_groups)
    assert all(st["step"].device.type == "cpu" and st["step"].dtype == torch.float32 for st in ob2.state.values())
    a2, b2 = GaussianParams(pa2, oa2), GaussianParams(pb2, ob2)
    g2 = torch.Generator().manual_seed(99)
    for _ in range(25):
        _step_both(a, b, g)
        _step_both(a2, b2, g2)
    _assert_same(a, b)
    _assert_same(b2, a2)   # (a2 started from b's state, b2 from a's: each pair from equal states)


def test_a_flagged_step_changes_nothing_on_the_device():
    _, b = _pair()
    g = torch.Generator().manual_seed(5)
    for k, gr in _grads(b.params, g).items():
        b.params[k].grad = gr
    b.opt.step()
    before = {k: v.detach().clone() for k, v in b.params.items()}
    moments = {k: b.opt.state[p]["exp_avg"].clone() for k, p in b.params.items()}
    for k, gr in _grads(b.params, g).items():
        b.params[k].grad = gr
    b.opt.found_inf = torch.ones(())
    b.opt.step()
    assert all(torch.equal(b.params[k].detach(), before[k]) for k in before)
    assert all(torch.equal(b.opt.state[p]["exp_avg"], moments[k]) for k, p in b.params.items())
    b.opt.found_inf = torch.zeros(())
    b.opt.step()
    assert not torch.equal(b.params["means"].detach(), before["means"])


def test_what_the_kernel_cannot_step_goes_to_torch():
    """float64 parameters: warp_adam gives torch's Adam; AMSGrad in a WarpAdam steps through torch's code."""
    p64 = torch.nn.Parameter(torch.randn(5, dtype=torch.float64))
    assert type(warp_adam([p64], lr=0.1)) is Adam
    p, q = torch.nn.Parameter(torch.ones(4)), torch.nn.Parameter(torch.ones(4))
    oa, ob = torch.optim.Adam([p], lr=0.1, amsgrad=True), WarpAdam([q], lr=0.1)
    ob.param_groups[0]["amsgrad"] = True
    for i in range(3):
        p.grad, q.grad = torch.full((4,), float(i) - 1.0), torch.full((4,), float(i) - 1.0)
        oa.step()
        ob.step()
    torch.testing.assert_close(q.detach(), p.detach())
    with pytest.raises(InputError, match="optimizer"):
        resolve(Recipe(optimizer="sgd"), "default", 100)


def test_the_trainer_trains_with_it():
    """Two steps of a run with each optimiser agree to float rounding. (Later steps drift apart where a
    gradient is rounding noise, e.g. the rotation of these isotropic Gaussians: Adam with eps 1e-15 turns
    its sign into a whole learning-rate step, whichever implementation rounds.)"""
    runs = {}
    for name in ("torch", "warp"):
        t = Trainer(_data(), scene=_scene(1), iters=6, recipe=Recipe(optimizer=name, sh_interval=3, sh_degree=1),
                    progress=False, device="cpu", seed=3)
        for _ in range(2):
            t.train_step()
        runs[name] = t
    assert isinstance(runs["warp"].opt, WarpAdam) and not isinstance(runs["torch"].opt, WarpAdam)
    for k, p in runs["torch"].params.items():
        torch.testing.assert_close(runs["warp"].params[k].detach(), p.detach(), rtol=1e-6, atol=1e-6, msg=k)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA_ONLY)])
def test_on_each_device_against_torchs_fused_adam(device):
    """Many steps (more than the pinned tables in turn on CUDA), rows pruned between them, a flagged step."""
    dev = torch.device(device)
    pa = {k: torch.nn.Parameter(v.detach().to(dev)) for k, v in _params().items()}
    pb = {k: torch.nn.Parameter(v.detach().to(dev)) for k, v in _params().items()}
    a = GaussianParams(pa, torch.optim.Adam(_groups(pa), eps=1e-15, fused=True))
    b = GaussianParams(pb, warp_adam(_groups(pb), eps=1e-15))
    assert isinstance(b.opt, WarpAdam)
    g = torch.Generator().manual_seed(6)
    for i in range(60):
        grads = {k: (torch.randn(p.shape, generator=g) * 0.1).to(dev) + 0.5 * p.detach() for k, p in a.params.items()}
        for k, gr in grads.items():
            a.params[k].grad, b.params[k].grad = gr.clone(), gr.clone()
        a.opt.step()
        b.opt.step()
        for x in (a, b):
            x.opt.zero_grad(set_to_none=True)
        if i == 30:
            for x in (a, b):
                x.keep(torch.arange(len(x), device=dev) % 4 != 0)
    for k in a.params:
        torch.testing.assert_close(b.params[k].detach().cpu(), a.params[k].detach().cpu(), **TOL, msg=k)
    before = b.params["means"].detach().clone()
    b.params["means"].grad = torch.ones_like(before)
    b.opt.found_inf = torch.ones((), device=dev)
    b.opt.step()
    assert torch.equal(b.params["means"].detach(), before)
