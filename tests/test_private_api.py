"""The one module that uses Warp's and torch's private APIs (ssgwarp/raster/private_api.py): its explicit version
gate, its self-tests (a probe launch replayed and compared with ``wp.launch``; torch's direct autograd entry and
fused Adam step compared with the public calls) and the public path taken, with the same results, wherever a
self-test disagrees or fails."""
from __future__ import annotations

import ctypes
import re
import warnings
from pathlib import Path

import pytest
import torch
import warp as wp

import ssgwarp.raster.launch as L
import ssgwarp.raster.private_api as P
from ssgwarp import rasterization

from test_rasterizer import make_cameras, make_scene

ROOT = Path(__file__).resolve().parents[1]

# the warp-lang ranges the adapter supports, one test each; pyproject.toml pins their union
SUPPORTED_RANGES = [((1, 19), (2, 0))]


def test_the_version_gate_is_the_pyproject_pin():
    pin = re.search(r'"warp-lang>=([\d.]+),<([\d.]+)"', (ROOT / "pyproject.toml").read_text())
    assert pin, "pyproject.toml pins warp-lang as >=A,<B"
    lo, hi = ((P.version_tuple(v) + (0,))[:2] for v in pin.groups())
    assert P.WARP_SUPPORTED == (lo, hi) == (SUPPORTED_RANGES[0][0], SUPPORTED_RANGES[-1][1])
    assert P.version_tuple("1.19.0") == (1, 19, 0) and P.version_tuple("1.20.1.dev0") == (1, 20, 1)
    assert P.in_supported_range((1, 19, 0)) and P.in_supported_range((1, 99, 3))
    assert not P.in_supported_range((1, 18, 9)) and not P.in_supported_range((2, 0, 0))


@pytest.mark.parametrize("lo, hi", SUPPORTED_RANGES, ids=lambda r: ".".join(map(str, r)))
def test_the_installed_warp_in_a_supported_range_takes_the_fast_path(lo, hi):
    """With the installed warp-lang in the range, its internals are the expected ones and the probe launch,
    replayed, equals ``wp.launch`` on the CPU (the self-test), so renders take the fast path there."""
    if not lo <= P.WARP_VERSION[:2] < hi:
        pytest.skip(f"warp-lang {wp.config.version} is not in [{lo}, {hi})")
    assert P.AVAILABLE and L.FAST
    tg = L.target(torch.zeros(1))
    assert tg.fast and P._FAST[tg.dkey] is True
    assert P._self_test(tg, None) is None          # (run again: every shortcut agrees with the public call)


@pytest.fixture
def fresh(monkeypatch):
    """No self-test result, target or recorded launch cached (restored afterwards)."""
    monkeypatch.setattr(P, "_FAST", {})
    monkeypatch.setattr(P, "_WARNED", set())
    monkeypatch.setattr(L, "_TARGETS", {})
    monkeypatch.setattr(L._LOCAL, "plans", {}, raising=False)


def _render():
    params = make_scene(30, dtype=torch.float32, seed=6)
    vm, K = make_cameras(1, 20, 16, dtype=torch.float32)
    m = params[0].clone().requires_grad_(True)
    img, alpha, _ = rasterization(m, *params[1:], vm, K, 20, 16)
    img.sum().backward()
    return img.detach(), alpha, m.grad


@pytest.mark.parametrize("fault", ["disagrees", "raises"])
def test_a_replay_that_disagrees_or_fails_sends_every_launch_through_wp_launch(fault, fresh, monkeypatch):
    if not P.AVAILABLE:
        pytest.skip("the fast path is not available with this Warp")
    want = _render()
    monkeypatch.setattr(P, "_FAST", {})
    monkeypatch.setattr(L, "_TARGETS", {})
    monkeypatch.setattr(L._LOCAL, "plans", {}, raising=False)
    run = P.Replay.run

    def broken(self, tg, dim, size, args, adj):
        if fault == "raises":
            raise OSError("a native call that is not there")
        run(self, tg, dim, size, args, adj)
        if adj is None and "probe" in self.kernel.key:
            (ctypes.c_float * 1).from_address(args[-12])[0] += 1.0   # (the probe's first output off by one)

    monkeypatch.setattr(P.Replay, "run", broken)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        got = _render()
    assert [str(w.message).split(" (")[0] for w in said] == ["ssgwarp: Warp's fast launch path on cpu did not pass "
                                                              "its self-test"]
    assert L.target(torch.zeros(1)).fast is False
    assert all(p.fast is None for p in L._LOCAL.plans.values())
    for a, b in zip(want, got):
        assert torch.equal(a, b)


@pytest.mark.parametrize("mode", ["no_grad", "inference_mode"])
def test_the_self_tests_pass_whatever_mode_their_first_caller_is_in(mode, fresh, monkeypatch):
    """The first render of a process may come under ``torch.no_grad()`` or ``torch.inference_mode()`` (``ssgwarp
    demo``'s first renders do): the self-tests run with gradients on all the same, and pass."""
    monkeypatch.setattr(P, "_APPLY_OK", [])
    monkeypatch.setattr(P, "_ADAM_OK", {})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with getattr(torch, mode)():
            _render_without_grad()
            assert P.function_apply(P._Probe) is not None and P._adam_works("cpu", torch.float32)
    assert P._APPLY_OK == [True] and L.target(torch.zeros(1)).fast is P.AVAILABLE


def _render_without_grad():
    params = make_scene(20, dtype=torch.float32, seed=9)
    vm, K = make_cameras(1, 16, 12, dtype=torch.float32)
    return rasterization(*params, vm, K, 16, 12)


def test_torchs_direct_autograd_entry_falls_back_to_function_apply_when_it_differs(monkeypatch):
    assert P.function_apply(P._Probe) is not None
    base = P._BASE_APPLY

    class Wrong:
        def __get__(self, obj, cls):
            bound = base.__get__(obj, cls)
            return lambda *a: tuple(t + 1 for t in bound(*a))

    monkeypatch.setattr(P, "_BASE_APPLY", Wrong())
    monkeypatch.setattr(P, "_APPLY_OK", [])
    monkeypatch.setattr(P, "_WARNED", set())
    with pytest.warns(RuntimeWarning, match="torch's direct autograd entry did not pass its self-test"):
        assert P.function_apply(P._Probe) is None
    img, _, _ = _render()                 # (the ops entered through Function.apply: the same image)
    monkeypatch.undo()
    assert torch.equal(img, _render()[0])


def test_the_fused_adam_step_falls_back_to_adam_step_when_it_differs(monkeypatch):
    from ssgwarp.core.optim import Adam
    from ssgwarp.reconstruction.step import adam_step

    monkeypatch.setattr(P, "_ADAM_OK", {})
    monkeypatch.setattr(P, "_WARNED", set())
    monkeypatch.setattr(P, "fused_adam_step", lambda groups, found_inf: None)   # (a step that updates nothing)
    p = torch.nn.Parameter(torch.ones(4))
    q = torch.nn.Parameter(torch.ones(4))
    opt_p, opt_q = (torch.optim.Adam([t], lr=0.1, fused=True) for t in (p, q))
    with pytest.warns(RuntimeWarning, match="the fused Adam step on cpu did not pass its self-test"):
        for i in range(3):
            p.grad, q.grad = torch.full((4,), i + 1.0), torch.full((4,), i + 1.0)
            adam_step(opt_p)
            opt_q.step()
    p.grad = torch.ones(4)
    assert P.fused_adam_groups(opt_p, (torch.optim.Adam, Adam)) is None
    assert torch.equal(p, q) and not torch.equal(p, torch.ones(4))

