"""The Adam every stage optimises with: torch's, fused into one kernel per parameter group and step.

On the CPU torch's default Adam loops over the parameters and runs a dozen small ops on each; its fused
CPU implementation updates each parameter in one pass (measured 2026-11-23, 2 cores, the 59 floats of
100,000 SH-3 Gaussians: 16.8 ms per step by default, 6.3 ms with ``foreach``, 2.0 ms fused). On CUDA
the default (``foreach``) launches about ten kernels per parameter group, and the reconstruction
keeps one group per parameter (its own learning rate): the launches alone cost about 1.5 ms of host
time per step (fern ``images_8``, H100), more than the GPU work of the whole step; fused, one launch
per group. The update is the same formula; only float rounding differs.

:class:`Adam` is torch's Adam run without ``torch._dynamo``: torch's optimizer methods are wrapped so that
``torch.compile`` leaves them alone, and the wrapper imports ``torch._dynamo`` (and with it sympy) the first
time one is called: about 1.5 s of a 2-core machine's time, a twentieth of the whole ``ssgwarp demo``. The
project compiles nothing, so :class:`Adam` calls the methods' own code (the same code, the same numbers).
"""
from __future__ import annotations

import inspect
import math
from typing import Iterable

import torch

_Optimizer = torch.optim.Optimizer


def _plain(method):
    """A torch optimizer method without its wrappers (``functools.wraps`` chains: the dynamo guard, the
    profiler hook torch patches onto ``step``)."""
    return inspect.unwrap(method)


class Adam(torch.optim.Adam):
    """``torch.optim.Adam`` whose methods run without importing ``torch._dynamo`` (see the module's text):
    the same state, state dicts (loadable into torch's Adam and back), step hooks and numbers."""

    def add_param_group(self, param_group: dict) -> None:
        _plain(_Optimizer.add_param_group)(self, param_group)

    def zero_grad(self, set_to_none: bool = True) -> None:
        _plain(_Optimizer.zero_grad)(self, set_to_none)

    def state_dict(self) -> dict:
        return _plain(_Optimizer.state_dict)(self)

    def load_state_dict(self, state_dict: dict) -> None:
        _plain(_Optimizer.load_state_dict)(self, state_dict)

    def step(self, closure=None):
        # (torch's step wrapper: gradients off unless the optimizer is differentiable, no graph breaks to mark)
        prev = torch.is_grad_enabled()
        try:
            torch.set_grad_enabled(self.defaults["differentiable"])
            return _plain(torch.optim.Adam.step)(self, closure)
        finally:
            torch.set_grad_enabled(prev)


def _devices(groups) -> set:
    out = set()
    for g in groups:
        params = g["params"] if isinstance(g, dict) else [g]
        if isinstance(params, torch.Tensor):
            params = [params]
        out.update((p.device.type, p.dtype) for p in params)
    return out


FUSED_DEVICES = ("cpu", "cuda")  # where torch has a fused Adam for float32 / float64 parameters


def fusable(kinds: set) -> bool:
    """Whether parameters of these ``(device type, dtype)`` kinds take torch's fused Adam: all on
    one device type that has it, all float32 or float64."""
    return (len({dev for dev, _ in kinds}) == 1 and all(dev in FUSED_DEVICES and dt in (torch.float32, torch.float64)
                                                      for dev, dt in kinds))


def adam(params: Iterable, **kwargs) -> Adam:
    """``torch.optim.Adam(params, **kwargs)`` (as :class:`Adam`), fused when every parameter is a float32/float64 tensor
    on the CPU or every one on CUDA (:func:`fusable`); an explicit ``fused`` or ``foreach`` wins."""
    groups = list(params)
    kinds = _devices(groups)
    if kinds and "fused" not in kwargs and "foreach" not in kwargs and fusable(kinds):
        kwargs["fused"] = True
    return Adam(groups, **kwargs)


def batch_factors(batch_size: int, scaling: str = "sqrt") -> tuple[float, float]:
    """``(lr factor, beta exponent)`` of Adam for ``batch_size`` views per step.

    ``"sqrt"``: learning rates x sqrt(B) (the square-root rule for adaptive optimizers: the mean
    gradient of B views has 1/sqrt(B) of one view's noise); ``"linear"``: x B; both raise Adam's
    betas to the power B, so the moments forget at the same rate per image seen. ``"none"``:
    one view's settings."""
    b = max(1, int(batch_size))
    if scaling == "none":
        return 1.0, 1.0
    return (math.sqrt(b) if scaling == "sqrt" else float(b)), float(b)
