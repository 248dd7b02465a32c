"""The Adam every stage optimises with: torch's, fused into one kernel per step where that is faster.

On the CPU torch's default Adam loops over the parameters and runs a dozen small ops on each; its fused
CPU implementation updates each parameter in one pass (measured 2026-11-23, 2 cores, the 59 floats of
100,000 SH-3 Gaussians: 16.8 ms per step by default, 6.3 ms with ``foreach``, 2.0 ms fused). On CUDA
torch's default (``foreach``) is kept. The update is the same formula; only float rounding differs.
"""
from __future__ import annotations

from typing import Iterable

import torch


def _devices(groups) -> set:
    out = set()
    for g in groups:
        params = g["params"] if isinstance(g, dict) else [g]
        if isinstance(params, torch.Tensor):
            params = [params]
        out.update((p.device.type, p.dtype) for p in params)
    return out


def adam(params: Iterable, **kwargs) -> torch.optim.Adam:
    """``torch.optim.Adam(params, **kwargs)``, fused when every parameter is a floating tensor on the CPU."""
    groups = list(params)
    kinds = _devices(groups)
    if kinds and "fused" not in kwargs and "foreach" not in kwargs and all(
            dev == "cpu" and dt in (torch.float32, torch.float64) for dev, dt in kinds):
        kwargs["fused"] = True
    return torch.optim.Adam(groups, **kwargs)
