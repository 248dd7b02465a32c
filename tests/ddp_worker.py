"""A data-parallel training run for tests/test_distributed.py, launched by ``torchrun``.

``python -m torch.distributed.run --nproc_per_node N tests/ddp_worker.py DATA_DIR OUT.pt [--steps S] [--diverge X.pt]``
trains the tiny capture in DATA_DIR (see :func:`make_trainer`) with one view per process and
per step, and the main process saves the final trainer state to OUT.pt. The test trains the
same capture in one process with the whole batch and compares. With ``--diverge``, the same
processes then start a second run of two steps in which rank 1 nudges one position: the
cross-rank check (``SSGWARP_DDP_CHECK=1``) must stop it with an error before X.pt is written.
"""
from __future__ import annotations

import argparse
import sys

import torch


class HeadHook:
    """Gaussian Grouping's shape of hook: a linear head on the identity channels, its own parameters."""

    def __init__(self, dim: int):
        g = torch.Generator().manual_seed(5)
        self.head = torch.nn.Linear(dim, 2)
        with torch.no_grad():
            self.head.weight.copy_(torch.randn(2, dim, generator=g))
            self.head.bias.zero_()
        self.calls = []

    def parameters(self):
        return [{"params": list(self.head.parameters()), "lr": 1e-2, "name": "head"}]

    def loss(self, step, view_index, identity_render):
        self.calls.append((step, view_index))
        return ((self.head(identity_render) - 0.5) ** 2).mean()


def make_trainer(data_dir, *, batch_size: int = 2, group=None, steps: int = 12, hook: bool = True):
    """Default strategy refining every 4 steps (clone, split, prune, an opacity reset), SH degree 1,
    identity encodings trained by a :class:`HeadHook`."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.strategy import DefaultStrategy
    from ssgwarp.reconstruction.trainer import Trainer

    data = load_dataset(data_dir, split_every=0)
    strategy = DefaultStrategy(max_gaussians=400, refine_start=4, refine_every=4, reset_every=8, grad_threshold=2e-5,
                               prune_opacity=0.02, prune_screen=0.4)
    return Trainer(data, iters=steps, recipe=Recipe(sh_degree=1, sh_interval=4), strategy=strategy, progress=False,
                   device="cpu",
                   seed=7, identity_dim=4 if hook else None, hooks=[HeadHook(4)] if hook else (),
                   batch_size=batch_size, group=group, backdrop="off")   # (the tiny cloud would get one)


def main() -> int:
    from ssgwarp.services import distributed

    ap = argparse.ArgumentParser()
    ap.add_argument("data_dir")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--diverge", help="then a run of 2 steps where rank 1 nudges one position (the check must "
                                      "stop it before this file is written)")
    a = ap.parse_args()
    group, _ = distributed.from_env(torch.device("cpu"))
    try:
        t = make_trainer(a.data_dir, batch_size=group.world_size, group=group, steps=a.steps)
        t.train()
        if group.is_main:
            torch.save({"state": t.state_dict(), "calls": t.hooks[0].calls}, a.out)
        if a.diverge:
            d = make_trainer(a.data_dir, batch_size=group.world_size, group=group, steps=2)
            if group.rank == 1:
                with torch.no_grad():
                    d.params["means"][0, 0] += 1e-4
            d.train()
            if group.is_main:
                torch.save({"state": d.state_dict()}, a.diverge)
    finally:
        distributed.shutdown(group)
    return 0


if __name__ == "__main__":
    code = main()
    from ssgwarp.services import distributed as _d

    _d.exit_after_group(code)  # as the CLI does under torchrun
    sys.exit(code)
