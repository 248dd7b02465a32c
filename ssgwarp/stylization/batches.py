"""Stage 2 over batches of views and several processes (``ssgwarp stylize --batch-size B``, ``torchrun``).

* :func:`batch_views`: the views of a step (consecutive runs of the one-view order, stateless,
  so a run resumes with any number of processes);
* :func:`batch_size_for`: the batch size over all processes (default one per process; it must
  divide between them);
* :func:`resumed_batch_size`: the batch size of the Stage 2 checkpoint a ``--resume`` continues;
  :func:`start_state` loads it into the parameters and Adam (every process takes the main one's);
* :func:`on_main_for_all`: the main process's key views and Stage 1 output, handed to the others
  (Stage 1 runs once; only the main process writes);
* :func:`batch_record`: ``metrics.json``'s ``world_size``, ``batch_size``, ``images_seen``, ``batch_scaling``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from ..errors import InputError


def view_order(step: int, num_views: int, seed: int) -> int:
    """The training view of one-view ``step``: a fresh seeded permutation every epoch (stateless, so resumable)."""
    epoch, k = divmod(step, num_views)
    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return int(torch.randperm(num_views, generator=g)[k])


def batch_views(step: int, batch_size: int, num_views: int, seed: int) -> list[int]:
    """The ``batch_size`` training views of ``step``: consecutive runs of the one-view order
    (:func:`view_order`), so a batch of B views sees the images B one-view steps see."""
    return [view_order(step * batch_size + j, num_views, seed) for j in range(batch_size)]


def batch_size_for(batch_size: Optional[int], group) -> int:
    """``batch_size`` (None: one view per process), checked to divide between ``group``'s processes."""
    b = int(batch_size) if batch_size is not None else group.world_size
    if b < 1:
        raise InputError(f"--batch-size {b}: must be >= 1")
    if b % group.world_size:
        raise InputError(f"--batch-size {b} cannot be split evenly between {group.world_size} processes; "
                         f"use a multiple of {group.world_size}")
    return b


def resumed_batch_size(checkpoint: Path, resume: bool) -> Optional[int]:
    """The batch size of the Stage 2 checkpoint ``--resume`` continues (None: not resuming, or none there)."""
    if not (resume and Path(checkpoint).is_file()):
        return None
    try:
        return int(torch.load(checkpoint, map_location="cpu", weights_only=False).get("batch_size", 1))
    except Exception:
        return None   # (unreadable: Stage 2 says so when it loads it)


def resume_state(checkpoint: Path, device, names: list[str], n: int, mode: str, batch: int) -> dict:
    """The Stage 2 checkpoint, checked to be of this run (parameters, scene size, mode) and batch size."""
    state = torch.load(checkpoint, map_location=device, weights_only=False)
    if state.get("params_names") != names or state.get("n") != n or state.get("mode") != mode:
        raise InputError(f"{checkpoint}: checkpoint is from a different run (mode, scene or options); "
                         f"use --force to start over")
    b = int(state.get("batch_size", 1))
    if b != batch:
        raise InputError(f"{checkpoint}: Stage 2 ran with --batch-size {b}, not {batch}; pass --batch-size {b} "
                         f"to resume it (with any number of processes dividing it) or --force to start over")
    return state


def start_state(params: dict, opt, checkpoint: Optional[Path], scene, mode: str, batch: int,
                group) -> tuple[int, list, float]:
    """Load ``checkpoint`` (when there) into the parameters and Adam; with several processes, every one
    takes the main one's parameters (then they step identically). Returns ``(step, history, seconds)``."""
    start, history, elapsed = 0, [], 0.0
    if checkpoint is not None and Path(checkpoint).is_file():
        state = resume_state(Path(checkpoint), scene.device, list(params), len(scene), mode, batch)
        with torch.no_grad():
            for n, p in params.items():
                p.copy_(state["params"][n])
        opt.load_state_dict(state["optimizer"])
        start, history, elapsed = int(state["step"]), list(state["history"]), float(state["seconds"])
    if group.active:
        mine = group.broadcast({n: p.detach().cpu() for n, p in params.items()})
        with torch.no_grad():
            for n, p in params.items():
                p.copy_(mine[n])
    return start, history, elapsed


def on_main_for_all(group, fn, device) -> tuple:
    """``fn()`` (a tuple of key views, stylized key views, a record) run by the main process alone and
    handed to every process (the exact tensors, through the process group); alone: ``fn()``."""
    if not group.active:
        return fn()
    kv, stylized, info = fn() if group.is_main else (None, None, None)
    box = (None if kv is None else kv.to("cpu"), None if stylized is None else stylized.cpu(), info)
    kv, stylized, info = group.broadcast(box)   # (the others send nothing: their box is empty)
    return (None if kv is None else kv.to(device)), (None if stylized is None else stylized.to(device)), info


def batch_record(result) -> dict:
    """What ``metrics.json`` says of a Stage 2 result's batches and processes."""
    b = result.batch
    return {"world_size": b["world_size"], "batch_size": b["batch_size"],
            "images_seen": result.iters_done * b["batch_size"],
            "batch_scaling": {k: b[k] for k in ("scaling", "lr_factor", "betas")}}
