"""Gaussian Grouping's training model: identity encodings, the linear group classifier and the losses (the
trained groups as the later stages read them, group maps included: :mod:`ssgwarp.raster.groups`).

Every Gaussian carries an identity vector ``e_i`` (``E = 16`` by default), rendered in the same
alpha-blending pass as colour into an identity image ``[H, W, E]``; a linear layer ``E -> K`` and
a softmax turn it into a group map. The losses (as in Gaussian Grouping): per-pixel cross entropy
against instance masks divided by ``log K`` (pixels marked ``IGNORE = -1`` do not count), and the
3D term, the KL divergence between sampled Gaussians' group distributions and those of their
nearest neighbours, divided by K. Training: :mod:`ssgwarp.grouping.train`; the stage:
:mod:`ssgwarp.grouping.stage`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..core.geometry import knn_indices, knn_table

Tensor = torch.Tensor
DEFAULT_DIM = 16
FORMAT = "ssgwarp-groups-1"


@dataclass(frozen=True)
class GroupConfig:
    """Training knobs (defaults documented in docs/grouping.md).

    dim: identity length E. iters: optimisation steps of the frozen-geometry stage.
    identity_lr, classifier_lr: Adam learning rates.
    views_per_step: training views rendered per step.
    reg_every, reg_weight, reg_k, reg_samples, reg_max_points: the 3D regulariser
        (every ``reg_every`` steps; ``reg_weight`` 0 turns it off; neighbours are
        searched among at most ``reg_max_points`` Gaussians).
    checkpoint_every: steps between checkpoints (Ctrl-C always writes one).
    """

    dim: int = DEFAULT_DIM
    iters: int = 1000
    identity_lr: float = 0.05
    classifier_lr: float = 0.025
    views_per_step: int = 1
    reg_every: int = 2
    reg_weight: float = 2.0
    reg_k: int = 5
    reg_samples: int = 1000
    reg_max_points: int = 200_000
    checkpoint_every: int = 500




def make_classifier(dim: int, num_groups: int, *, generator: Optional[torch.Generator] = None,
                    device=None, dtype=torch.float32) -> torch.nn.Linear:
    """``nn.Linear(dim, num_groups)`` initialised from ``generator`` (uniform ±1/sqrt(dim), as torch's default)."""
    if dim < 1 or num_groups < 1:
        raise InputError(f"group classifier: need dim >= 1 and K >= 1, got dim={dim}, K={num_groups}")
    lin = torch.nn.Linear(dim, num_groups, device=device, dtype=dtype)
    bound = 1.0 / math.sqrt(dim)
    with torch.no_grad():
        w = torch.rand(num_groups, dim, generator=generator, dtype=torch.float64) * 2 - 1
        b = torch.rand(num_groups, generator=generator, dtype=torch.float64) * 2 - 1
        lin.weight.copy_((w * bound).to(lin.weight))
        lin.bias.copy_((b * bound).to(lin.bias))
    return lin


def init_identities(n: int, dim: int, *, generator: Optional[torch.Generator] = None, device=None,
                    dtype=torch.float32) -> Tensor:
    """``[n, dim]`` initial identity encodings, N(0, 0.5^2) from ``generator``."""
    return (torch.randn(n, dim, generator=generator, dtype=torch.float64) * 0.5).to(device=device, dtype=dtype)












def mask_loss(logits: Tensor, targets: Tensor, num_groups: int) -> Tensor:
    """Cross entropy of ``logits [..., K]`` against ``targets [...]`` (long, ``IGNORE`` skipped) / log K.

    Returns 0 (with a graph) when no pixel is labelled; K = 1 is divided by 1.
    """
    flat_t = targets.reshape(-1).to(logits.device).long()
    flat_l = logits.reshape(-1, logits.shape[-1])
    valid = flat_t >= 0   # (ignored pixels as cross_entropy's ignore_index: no boolean indexing, no host sync)
    ce = F.cross_entropy(flat_l, torch.where(valid, flat_t, -100), ignore_index=-100, reduction="sum") \
        / valid.sum().clamp_min(1)
    return ce / math.log(num_groups) if num_groups > 1 else ce


def regularizer_3d(identities: Tensor, means: Tensor, classifier: torch.nn.Linear, *,
                   generator: torch.Generator, k: int = 5, samples: int = 1000,
                   max_points: int = 200_000, neighbours: Optional[Tensor] = None) -> Tensor:
    """The 3D consistency term: mean KL(p_i || p_j) over sampled Gaussians i and their k nearest j, / K.

    Args:
        identities: ``[N, E]`` (differentiable). means: ``[N, 3]`` (positions; no gradient taken).
        generator: CPU generator for the samples.
        neighbours: ``[N, >= k]`` each Gaussian's nearest others, nearest first
            (:func:`neighbour_table`: positions that do not move, e.g. a frozen scene's), used
            instead of a search per call when ``N <= max_points``; the same samples and value.
    Neighbours are searched among a random subset of at most ``max_points``
    Gaussians (all when N is smaller); the sample itself is excluded. Only the sampled
    Gaussians and their neighbours go through the classifier.
    """
    n = identities.shape[0]
    if n < 2:
        return identities.sum() * 0.0
    dev = identities.device
    if n > max_points:
        pool = torch.randperm(n, generator=generator)[:max_points].to(dev)
    else:
        pool = torch.arange(n, device=dev)
    m = min(samples, pool.numel())
    pick = torch.randperm(pool.numel(), generator=generator)[:m].to(dev)
    q = pool[pick]
    if neighbours is not None and n <= max_points and neighbours.shape[1] >= min(k, n - 1):
        nbr = neighbours[q, :min(k, n - 1)].to(dev)                       # [m, k] (pool is every Gaussian)
    else:
        with torch.no_grad():
            pts = means.detach()[pool]
            nbr_local = knn_indices(pts[pick], pts, k, exclude=pick)
        nbr = pool[nbr_local]                                        # [m, k]
    rows = torch.cat([q[:, None], nbr], dim=1)                       # [m, 1 + k]
    logp = torch.log_softmax(classifier(identities[rows]), dim=-1)   # [m, 1 + k, K]
    lp_q, lp_n = logp[:, :1], logp[:, 1:]
    kl = (lp_q.exp() * (lp_q - lp_n)).sum(-1)                        # [m, k]
    return kl.mean() / logp.shape[-1]


def neighbour_table(means: Tensor, config: "GroupConfig") -> Optional[Tensor]:
    """``[N, reg_k]`` each Gaussian's nearest others (:func:`ssgwarp.core.geometry.knn_table`) for
    :func:`regularizer_3d` on positions that stay fixed, or None when the regulariser is off or
    draws its neighbours from a random pool (``N > reg_max_points``)."""
    n = means.shape[0]
    if config.reg_weight <= 0 or config.reg_every <= 0 or n < 2 or n > config.reg_max_points:
        return None
    return knn_table(means.detach(), config.reg_k)
