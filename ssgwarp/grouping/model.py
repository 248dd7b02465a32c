"""Gaussian Grouping's model: identity encodings, the linear group classifier, group maps and losses.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch
import torch.nn.functional as F
from ..core.progress import tqdm

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.fileio import read_json
from ..core.geometry import knn_indices, knn_table
from ..raster.scene import GaussianScene

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


@dataclass
class GroupModel:
    """A trained group classifier: ``classifier`` (``nn.Linear`` E→K), ``num_groups`` K, ``dim`` E, ``info`` (groups.json)."""

    classifier: torch.nn.Linear
    num_groups: int
    dim: int
    info: dict = field(default_factory=dict)


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


def _copy_linear(classifier: torch.nn.Linear, device, dtype) -> torch.nn.Linear:
    lin = torch.nn.Linear(classifier.in_features, classifier.out_features, device=device, dtype=dtype)
    with torch.no_grad():
        lin.weight.copy_(classifier.weight)
        lin.bias.copy_(classifier.bias)
    return lin


def _iter_group_probs(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                      progress: bool = False, **raster_kwargs):
    """Yield ``probs [H, W, K]`` camera by camera."""
    if scene.identities is None:
        raise InputError("scene has no identity encodings: run `ssgwarp group` first")
    if scene.identities.shape[1] != classifier.in_features:
        raise InputError(f"identity length {scene.identities.shape[1]} does not match the classifier's "
                         f"input {classifier.in_features}")
    clf = _copy_linear(classifier, scene.device, scene.dtype)
    with torch.no_grad():
        for c in tqdm(range(len(cameras)), desc="group maps", unit="view", leave=False,
                      disable=not progress):
            img, _, _ = scene.render(cameras[c].to(scene.device), identities=True, rgb=False, **raster_kwargs)
            yield torch.softmax(clf(img[0]), dim=-1)


def render_group_maps(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                      progress: bool = False, **raster_kwargs) -> tuple[Tensor, Tensor]:
    """Group maps of ``cameras``.

    The identity channels are rendered (one pass per camera, no RGB), the
    classifier is applied per pixel and a softmax taken. Pixels no Gaussian
    covers render identity 0 and so take the class of the classifier's bias.

    Returns:
        ``labels [C, H, W]`` long in ``0..K-1`` and ``probs [C, H, W, K]`` (on the scene's device).
    """
    probs = list(_iter_group_probs(scene, cameras, classifier, progress=progress, **raster_kwargs))
    probs = torch.stack(probs)
    return probs.argmax(dim=-1), probs


def group_labels(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                 progress: bool = False) -> Tensor:
    """``[C, H, W]`` group maps only, kept on the CPU as int16 (memory-light for many large views)."""
    out = [p.argmax(dim=-1).to("cpu", torch.int16)
           for p in _iter_group_probs(scene, cameras, classifier, progress=progress)]
    return torch.stack(out)


def gaussian_groups(scene: GaussianScene, classifier: torch.nn.Linear) -> tuple[Tensor, Tensor]:
    """Classify each Gaussian's own identity vector: ``(ids [N] long, prob [N])`` (the winning probability)."""
    if scene.identities is None:
        raise InputError("scene has no identity encodings: run `ssgwarp group` first")
    clf = _copy_linear(classifier, scene.device, scene.dtype)
    with torch.no_grad():
        p = torch.softmax(clf(scene.identities), dim=-1)
        prob, ids = p.max(dim=-1)
    return ids, prob


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


def load_groups(scene_dir: str | Path, device=None) -> GroupModel:
    """The classifier of a grouped run (``SCENE_DIR/groups/classifier.pt``) as a :class:`GroupModel`."""
    scene_dir = Path(scene_dir)
    path = scene_dir / "groups" / "classifier.pt"
    if not path.is_file():
        raise InputError(f"{scene_dir}: not grouped (no {path}); run `ssgwarp group {scene_dir}` first")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
        dim, k = int(obj["dim"]), int(obj["num_groups"])
        lin = torch.nn.Linear(dim, k)
        lin.load_state_dict(obj["state_dict"])
    except (KeyError, RuntimeError, ValueError, EOFError) as e:
        raise InputError(f"{path}: not a valid group classifier ({e}); rerun `ssgwarp group --force`") from None
    lin = lin.to(device if device is not None else "cpu").requires_grad_(False)
    info = read_json(scene_dir / "groups" / "groups.json") if (scene_dir / "groups" / "groups.json").is_file() else {}
    return GroupModel(classifier=lin, num_groups=k, dim=dim, info=info)
