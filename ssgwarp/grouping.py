"""Gaussian Grouping: identity encodings, a linear group classifier and group maps (``ssgwarp group``).

Every Gaussian carries an identity vector ``e_i`` (``E = 16`` by default). It
is rendered in the same alpha-blending pass as colour, giving an identity image
``[H, W, E]``; a linear layer ``E -> K`` and a softmax turn it into a group map.
Training (as in Gaussian Grouping):

- 2D: per-pixel cross entropy against instance masks, divided by ``log K``
  (pixels marked ``IGNORE = -1`` do not count);
- 3D: every ``reg_every`` steps, ``reg_samples`` Gaussians are drawn and the KL
  divergence between each one's group distribution and those of its
  ``reg_k`` nearest neighbours (by position) is averaged, divided by K and
  weighted by ``reg_weight``.

Masks come from ``ssgwarp masks`` (:mod:`ssgwarp.masks`: Segment Anything
instances associated across views, ``RUN/object_mask``), from outside
(``object_mask/<image stem>.png``, integer ids consistent across views) or,
without either, from the scene itself (:mod:`ssgwarp.pseudomasks`);
``groups.json`` ``kind`` says which. Training runs either as a stage on a
reconstructed scene with geometry frozen (only identities and classifier are
optimised) or jointly with reconstruction (``--joint``, through
:class:`GroupingHook`).

Public API:
    GroupConfig, GroupModel, GroupingHook
    make_classifier(dim, k, generator)             -> nn.Linear
    render_group_maps(scene, cameras, classifier)  -> (labels [C,H,W] long, probs [C,H,W,K])
    gaussian_groups(scene, classifier)             -> (ids [N] long, prob [N])
    mask_loss(logits, targets, k)                  -> scalar
    regularizer_3d(identities, means, classifier)  -> scalar
    load_masks(mask_dir, names, width, height)     -> MaskSet
    train_identities(scene, cameras, targets, k)   -> (scene, classifier, history)
    reprojection_agreement(scene, cameras, labels) -> dict
    group_scene(scene_dir, ...)                    -> summary dict (what the CLI runs)
    load_groups(scene_dir, device)                 -> GroupModel
    add_arguments(parser), run(args)               -> the CLI
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .cameras import Cameras
from .errors import InputError, SsgwarpError
from .fileio import atomic_path, read_json, write_image, write_json
from .pseudomasks import IGNORE, ClusterConfig
from .scene import GaussianScene

Tensor = torch.Tensor
DEFAULT_DIM = 16
FORMAT = "ssgwarp-groups-1"
# which kind of groups a run used (groups.json "kind")
KINDS = {"segmenter": "segmenter instances", "masks": "given masks", "mask-free": "mask-free clusters"}


# -- configuration and the model -------------------------------------------------------

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


# -- rendering and classifying -------------------------------------------------------------

def _copy_linear(classifier: torch.nn.Linear, device, dtype) -> torch.nn.Linear:
    lin = torch.nn.Linear(classifier.in_features, classifier.out_features, device=device, dtype=dtype)
    with torch.no_grad():
        lin.weight.copy_(classifier.weight)
        lin.bias.copy_(classifier.bias)
    return lin


def _iter_group_probs(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                      progress: bool = False, **raster_kwargs):
    """Yield ``probs [H, W, K]`` camera by camera."""
    from tqdm.auto import tqdm

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


# -- losses -----------------------------------------------------------------------------------

def mask_loss(logits: Tensor, targets: Tensor, num_groups: int) -> Tensor:
    """Cross entropy of ``logits [..., K]`` against ``targets [...]`` (long, ``IGNORE`` skipped) / log K.

    Returns 0 (with a graph) when no pixel is labelled; K = 1 is divided by 1.
    """
    flat_t = targets.reshape(-1).to(logits.device).long()
    flat_l = logits.reshape(-1, logits.shape[-1])
    valid = flat_t >= 0
    if not bool(valid.any()):
        return flat_l.sum() * 0.0
    ce = F.cross_entropy(flat_l[valid], flat_t[valid])
    return ce / math.log(num_groups) if num_groups > 1 else ce


def knn_indices(queries: Tensor, points: Tensor, k: int, *, exclude: Optional[Tensor] = None,
                chunk: int = 65536) -> Tensor:
    """``[M, k]`` indices into ``points [P, 3]`` of each query's k nearest points.

    ``exclude [M]`` (an index into ``points`` per query, e.g. the query itself)
    is never returned. Exact, chunked over the points.
    """
    M, P = queries.shape[0], points.shape[0]
    k = min(k, P - (1 if exclude is not None else 0))
    best_d = torch.full((M, 0), float("inf"), dtype=queries.dtype, device=queries.device)
    best_i = torch.zeros((M, 0), dtype=torch.long, device=queries.device)
    for s in range(0, P, chunk):
        d = torch.cdist(queries, points[s:s + chunk])
        idx = torch.arange(s, s + d.shape[1], device=queries.device)[None].expand(M, -1)
        if exclude is not None:
            d = d.masked_fill(idx == exclude[:, None], float("inf"))
        d = torch.cat([best_d, d], dim=1)
        idx = torch.cat([best_i, idx], dim=1)
        top = d.topk(min(k, d.shape[1]), dim=1, largest=False)
        best_d, best_i = top.values, idx.gather(1, top.indices)
    return best_i


def regularizer_3d(identities: Tensor, means: Tensor, classifier: torch.nn.Linear, *,
                   generator: torch.Generator, k: int = 5, samples: int = 1000,
                   max_points: int = 200_000) -> Tensor:
    """The 3D consistency term: mean KL(p_i || p_j) over sampled Gaussians i and their k nearest j, / K.

    Args:
        identities: ``[N, E]`` (differentiable). means: ``[N, 3]`` (positions; no gradient taken).
        generator: CPU generator for the samples.
    Neighbours are searched among a random subset of at most ``max_points``
    Gaussians (all when N is smaller); the sample itself is excluded.
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
    with torch.no_grad():
        pts = means.detach()[pool]
        nbr_local = knn_indices(pts[pick], pts, k, exclude=pick)
    nbr = pool[nbr_local]                                    # [m, k]
    logp = torch.log_softmax(classifier(identities), dim=-1)  # [N, K]
    lp_q = logp[q][:, None, :]                               # [m, 1, K]
    lp_n = logp[nbr]                                         # [m, k, K]
    kl = (lp_q.exp() * (lp_q - lp_n)).sum(-1)                # [m, k]
    return kl.mean() / logp.shape[1]


# -- masks from outside -------------------------------------------------------------------

@dataclass
class MaskSet:
    """Instance masks at training resolution.

    targets: ``[C, H, W]`` long, compact ids ``0..M-1`` (``IGNORE`` where the
        mask holds ``ignore_id``); ``ids``: the original mask value of each
        compact id; ``num_groups``: K (>= M).
    """

    targets: Tensor
    ids: list[int]
    num_groups: int
    files: list[str]


def _read_id_image(path: Path) -> np.ndarray:
    """``[H, W]`` integer ids of a single-channel (or grey-as-RGB) mask image, in its native bit depth."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read mask image ({oiio.geterror()})")
    try:
        spec = inp.spec()
        fmt = spec.format
        data = inp.read_image(0, 0, 0, spec.nchannels, fmt)
    finally:
        inp.close()
    if data is None or not isinstance(data, np.ndarray):
        raise InputError(f"{path}: cannot decode mask image")
    arr = np.asarray(data).reshape(spec.height, spec.width, spec.nchannels)
    if arr.dtype.kind == "f":
        raise InputError(f"{path}: mask images must hold integer ids (8- or 16-bit PNG), got float data")
    channels = arr.shape[2]
    if channels in (2, 4):          # drop alpha
        arr = arr[..., : channels - 1]
    if arr.shape[2] > 1 and not all(np.array_equal(arr[..., 0], arr[..., c]) for c in range(1, arr.shape[2])):
        raise InputError(f"{path}: a mask must be a single-channel image of integer ids, "
                         f"got {arr.shape[2]} differing colour channels")
    return arr[..., 0].astype(np.int64)


def _resize_nearest(ids: np.ndarray, width: int, height: int) -> np.ndarray:
    h, w = ids.shape
    if (w, h) == (width, height):
        return ids
    ys = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return ids[ys[:, None], xs[None, :]]


def find_mask(mask_dir: Path, name: str) -> Optional[Path]:
    """``mask_dir/<name>.png`` or ``mask_dir/<stem of name>.png``, whichever exists."""
    for cand in (mask_dir / f"{name}.png", mask_dir / f"{Path(name).stem}.png"):
        if cand.is_file():
            return cand
    return None


def load_masks(mask_dir: str | Path, names: Sequence[str], width: int, height: int, *,
               num_groups: Optional[int] = None, ignore_id: Optional[int] = None,
               required: Optional[Sequence[bool]] = None, aspect_tol: float = 0.02) -> MaskSet:
    """Load Gaussian Grouping's ``object_mask/<image stem>.png`` for each of ``names``.

    Masks are resized by nearest neighbour to ``width`` x ``height``; their ids
    (all values but ``ignore_id``) are made compact in sorted order. K is the
    number of distinct ids unless ``num_groups`` is given.

    ``required[i]`` False lets image i have no mask (its targets are all
    ``IGNORE``). Raises InputError for: a missing folder, a required mask
    missing (named), an aspect ratio that differs from the image's by more
    than ``aspect_tol`` (relative), a non-integer or colour mask, more ids than
    ``num_groups``.
    """
    mask_dir = Path(mask_dir)
    if not mask_dir.is_dir():
        raise InputError(f"--masks {mask_dir}: folder not found")
    required = [True] * len(names) if required is None else list(required)
    raw, files = [], []
    for name, req in zip(names, required):
        p = find_mask(mask_dir, name)
        if p is None:
            if req:
                raise InputError(f"{mask_dir}: no mask for image '{name}' (expected {mask_dir / (Path(name).stem + '.png')})")
            raw.append(None)
            files.append("")
            continue
        ids = _read_id_image(p)
        h, w = ids.shape
        if abs((w / h) / (width / height) - 1.0) > aspect_tol:
            raise InputError(f"{p}: mask is {w}x{h} (aspect {w / h:.3f}) but image '{name}' is trained at "
                             f"{width}x{height} (aspect {width / height:.3f}); masks must match the images' aspect ratio")
        raw.append(_resize_nearest(ids, width, height))
        files.append(str(p))
    if all(r is None for r in raw):
        raise InputError(f"{mask_dir}: no masks found for any image")
    values = np.unique(np.concatenate([r.reshape(-1) for r in raw if r is not None]))
    if ignore_id is not None:
        values = values[values != ignore_id]
    m = int(values.size)
    if m == 0:
        raise InputError(f"{mask_dir}: the masks hold no ids (every pixel is the ignore id {ignore_id})")
    k = m if num_groups is None else int(num_groups)
    if m > k:
        shown = ", ".join(str(int(v)) for v in values[:12]) + (" ..." if m > 12 else "")
        raise InputError(f"{mask_dir}: the masks hold {m} distinct ids ({shown}) but --groups is {k}; "
                         f"raise --groups to at least {m} or leave it out")
    lut = {int(v): i for i, v in enumerate(values)}
    targets = torch.full((len(names), height, width), IGNORE, dtype=torch.long)
    for i, r in enumerate(raw):
        if r is None:
            continue
        compact = np.full(r.shape, IGNORE, dtype=np.int64)
        for v, j in lut.items():
            compact[r == v] = j
        targets[i] = torch.from_numpy(compact)
    return MaskSet(targets=targets, ids=[int(v) for v in values], num_groups=k, files=files)


# -- training (frozen geometry) -------------------------------------------------------------

def _adam(identities: Tensor, classifier: torch.nn.Linear, config: GroupConfig) -> torch.optim.Adam:
    return torch.optim.Adam([
        {"params": [identities], "lr": config.identity_lr, "name": "identities"},
        {"params": list(classifier.parameters()), "lr": config.classifier_lr, "name": "classifier"},
    ])


def _save_checkpoint(path: Path, step: int, identities: Tensor, classifier: torch.nn.Linear,
                     opt: torch.optim.Optimizer, gen_state: Tensor, meta: dict, history: list,
                     order: list) -> None:
    obj = {"step": step, "identities": identities.detach().cpu(), "classifier": classifier.state_dict(),
           "optimizer": opt.state_dict(), "generator": gen_state, "meta": meta, "history": history,
           "order": list(order)}
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def train_identities(scene: GaussianScene, cameras: Cameras, targets: Tensor, num_groups: int, *,
                     config: GroupConfig = GroupConfig(), seed: int = 0, progress: bool = True,
                     checkpoint_path: Optional[str | Path] = None, resume: bool = False,
                     ) -> tuple[GaussianScene, torch.nn.Linear, list[dict]]:
    """Train identities and classifier with the geometry frozen.

    Args:
        scene: the reconstructed scene (its geometry and colour are not changed).
        cameras: the C training cameras. targets: ``[C, H, W]`` long masks
        (``IGNORE`` = -1 skipped). num_groups: K.
        checkpoint_path: where checkpoints go (every ``config.checkpoint_every``
        steps and on Ctrl-C); with ``resume`` a compatible one is continued.
    Returns:
        ``(scene with identities [N, E], classifier, history)``; history holds
        ``{"step", "ce", "reg"}`` every 10 steps (``reg`` None on steps without
        the 3D term). Deterministic for a seed.
    """
    from tqdm.auto import tqdm

    C = len(cameras)
    if targets.shape != (C, cameras.height, cameras.width):
        raise InputError(f"targets must be [C={C}, H={cameras.height}, W={cameras.width}], got {tuple(targets.shape)}")
    dev, dt = scene.device, scene.dtype
    gen = torch.Generator().manual_seed(int(seed))
    geom = scene.detach().replace(identities=None)
    n = len(geom)
    identities = init_identities(n, config.dim, generator=gen, device=dev, dtype=dt).requires_grad_(True)
    classifier = make_classifier(config.dim, num_groups, generator=gen, device=dev, dtype=dt)
    opt = _adam(identities, classifier, config)
    targets = targets.to("cpu", torch.int16 if num_groups < 32767 else torch.long)  # moved per step
    cams = cameras.to(dev)
    history: list[dict] = []
    order: list[int] = []
    meta = {"n": n, "dim": config.dim, "num_groups": num_groups, "seed": int(seed), "views": C}
    start = 0
    ckpt = Path(checkpoint_path) if checkpoint_path is not None else None
    if resume and ckpt is not None and ckpt.is_file():
        state = torch.load(ckpt, map_location=dev, weights_only=False)
        if state.get("meta") != meta:
            raise InputError(f"{ckpt}: checkpoint was written for a different setup ({state.get('meta')} vs {meta}); "
                             "rerun with --force to start over")
        with torch.no_grad():
            identities.copy_(state["identities"].to(dev, dt))
        classifier.load_state_dict(state["classifier"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        start = int(state["step"])
        history = list(state["history"])
        order = list(state.get("order", []))
    if num_groups == 1 or C == 0:
        start = config.iters  # nothing to learn: every pixel is group 0

    def next_views() -> list[int]:
        nonlocal order
        out = []
        while len(out) < min(config.views_per_step, C):
            if not order:
                order = torch.randperm(C, generator=gen).tolist()
            out.append(order.pop())
        return out

    done = start          # steps whose update has been applied
    snap = None           # (generator state, view order) at the start of an unfinished step
    bar = tqdm(total=config.iters, initial=start, desc="grouping", unit="it", disable=not progress)
    try:
        for step in range(start, config.iters):
            snap = (gen.get_state(), list(order))
            views = next_views()
            s = geom.replace(identities=identities)
            img, _, _ = s.render(cams[views], identities=True, rgb=False)
            logits = classifier(img)
            ce = mask_loss(logits, targets[views].to(dev), num_groups)
            loss = ce
            reg_v = None
            if config.reg_weight > 0 and config.reg_every > 0 and step % config.reg_every == 0:
                reg = regularizer_3d(identities, geom.means, classifier, generator=gen, k=config.reg_k,
                                     samples=config.reg_samples, max_points=config.reg_max_points)
                loss = loss + config.reg_weight * reg
                reg_v = float(reg.detach())
            if not torch.isfinite(loss.detach()):
                if ckpt is not None:  # the parameters are still those of the last good step
                    _save_checkpoint(ckpt, done, identities, classifier, opt, snap[0], meta, history, snap[1])
                raise SsgwarpError(f"grouping: the loss became {float(loss.detach())} at step {step + 1} of "
                                   f"{config.iters}; the last good state is kept in the checkpoint (lower the "
                                   "learning rate and rerun with --resume)")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            done, snap = step + 1, None
            if step % 10 == 0 or step == config.iters - 1:
                history.append({"step": step, "ce": float(ce.detach()), "reg": reg_v})
                bar.set_postfix(ce=f"{float(ce.detach()):.4f}")
            bar.update(1)
            if ckpt is not None and config.checkpoint_every > 0 and done % config.checkpoint_every == 0 \
                    and done < config.iters:
                _save_checkpoint(ckpt, done, identities, classifier, opt, gen.get_state(), meta, history, order)
    except KeyboardInterrupt:
        if ckpt is not None:
            # an unfinished step is dropped and replayed on resume (same views, same samples)
            g_state, o = snap if snap is not None else (gen.get_state(), order)
            _save_checkpoint(ckpt, done, identities, classifier, opt, g_state, meta, history, o)
        raise
    finally:
        bar.close()
    out = scene.detach().replace(identities=identities.detach().clone())
    classifier.requires_grad_(False)
    return out, classifier, history


# -- joint training with reconstruction -----------------------------------------------------

class GroupingHook:
    """Joint training with reconstruction: a hook for ``ssgwarp.reconstruct.Trainer(..., hooks=[...])``.

    The Trainer renders the identity channels with colour, optimises
    ``scene.identities`` itself and densifies every scene tensor; the hook
    contributes the classifier's parameter group and the grouping loss.

    Args:
        targets: ``[C, H, W]`` long masks, row ``i`` for the Trainer's view index ``i``
            (all-``IGNORE`` rows for views without masks).
        num_groups: K. config: :class:`GroupConfig`. seed: classifier init and
            regulariser samples.
    """

    def __init__(self, targets: Tensor, num_groups: int, *, config: GroupConfig = GroupConfig(), seed: int = 0,
                 device=None, dtype=torch.float32):
        self.config = config
        self.num_groups = int(num_groups)
        self.dim = int(config.dim)
        self.generator = torch.Generator().manual_seed(int(seed) + 7919)
        self.classifier = make_classifier(self.dim, self.num_groups, generator=self.generator,
                                          device=device, dtype=dtype)
        self.targets = targets
        self.scene_fn = None      # callable returning the Trainer's current scene (for the 3D regulariser)
        self.last: dict = {}

    def parameters(self) -> list[dict]:
        """The classifier's Adam parameter group."""
        return [{"params": list(self.classifier.parameters()), "lr": self.config.classifier_lr,
                 "name": "group_classifier"}]

    def loss(self, step: int, view_index: int, identity_render: Tensor, scene: Optional[GaussianScene] = None) -> Tensor:
        """Grouping loss of one rendered view: ``identity_render [H, W, E]`` (or ``[B, H, W, E]``) → scalar."""
        cls = self.classifier
        if cls.weight.device != identity_render.device:
            cls.to(identity_render.device)
        t = self.targets[view_index].to(identity_render.device)
        ce = mask_loss(cls(identity_render), t, self.num_groups)
        loss = ce
        self.last = {"ce": float(ce.detach())}
        if scene is None and self.scene_fn is not None:
            scene = self.scene_fn()
        cfg = self.config
        if scene is not None and scene.identities is not None and cfg.reg_weight > 0 and cfg.reg_every > 0 \
                and step % cfg.reg_every == 0:
            reg = regularizer_3d(scene.identities, scene.means, cls, generator=self.generator, k=cfg.reg_k,
                                 samples=cfg.reg_samples, max_points=cfg.reg_max_points)
            loss = loss + cfg.reg_weight * reg
            self.last["reg"] = float(reg.detach())
        return loss


# -- multi-view agreement ------------------------------------------------------------------

def neighbour_pairs(cameras: Cameras, ids: Optional[Sequence[int]] = None) -> list[tuple[int, int]]:
    """Each camera of ``ids`` paired with its nearest other camera (centre distance + viewing angle)."""
    ids = list(range(len(cameras))) if ids is None else list(ids)
    if len(ids) < 2:
        return []
    c = cameras.centers.double()[ids]
    f = cameras.forwards.double()[ids]
    d = torch.cdist(c, c)
    scale = d[d > 0].median() if bool((d > 0).any()) else torch.tensor(1.0, dtype=d.dtype)
    cost = d / scale + (1.0 - f @ f.T)
    cost.fill_diagonal_(float("inf"))
    j = cost.argmin(dim=1).tolist()
    return [(ids[a], ids[b]) for a, b in enumerate(j)]


def reprojection_agreement(scene: GaussianScene, cameras: Cameras, labels: Tensor,
                           pairs: Optional[Sequence[tuple[int, int]]] = None, *, alpha_min: float = 0.5,
                           depth_tol: float = 0.05) -> dict:
    """How often group maps agree across views, by reprojecting pixels with the rendered depth.

    Each pixel of view a (alpha >= ``alpha_min``) is lifted with its expected
    depth, projected into view b and compared with b's label there; only
    pixels that land inside b, on a covered pixel whose depth agrees within
    ``depth_tol`` (relative; occlusion test) count.

    Args:
        labels: ``[C, H, W]`` group maps of ``cameras``. pairs: ``(a, b)`` camera
        indices, default :func:`neighbour_pairs`.
    Returns:
        ``{"mean": fraction over all counted pixels, "pairs": [{"a", "b", "agreement", "pixels"}]}``.
    """
    pairs = neighbour_pairs(cameras) if pairs is None else list(pairs)
    dev, dt = scene.device, scene.dtype
    cams = cameras.to(dev, dt)
    need = sorted({i for p in pairs for i in p})
    depth, alpha = {}, {}
    with torch.no_grad():
        for i in need:
            d, a, _ = scene.render(cams[i], render_mode="ED")
            depth[i], alpha[i] = d[0, ..., 0], a[0, ..., 0]
    H, W = cams.height, cams.width
    ys, xs = torch.meshgrid(torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt),
                            indexing="ij")
    out, tot_agree, tot = [], 0, 0
    for a, b in pairs:
        Ka, Kb = cams.Ks[a], cams.Ks[b]
        da = depth[a]
        ok = alpha[a] >= alpha_min
        x = (xs + 0.5 - Ka[0, 2]) / Ka[0, 0] * da
        y = (ys + 0.5 - Ka[1, 2]) / Ka[1, 1] * da
        pc = torch.stack([x, y, da, torch.ones_like(da)], dim=-1)                 # [H,W,4] camera a
        pw = pc @ cams.camtoworlds[a].T
        pb = pw @ cams.viewmats[b].T
        zb = pb[..., 2]
        ub = Kb[0, 0] * pb[..., 0] / zb.clamp_min(1e-9) + Kb[0, 2]
        vb = Kb[1, 1] * pb[..., 1] / zb.clamp_min(1e-9) + Kb[1, 2]
        ok = ok & (zb > 1e-6) & (ub >= 0) & (ub < W) & (vb >= 0) & (vb < H)
        ui = ub.floor().long().clamp(0, W - 1)
        vi = vb.floor().long().clamp(0, H - 1)
        db = depth[b][vi, ui]
        ok = ok & (alpha[b][vi, ui] >= alpha_min) & ((db - zb).abs() <= depth_tol * zb.abs())
        same = (labels[a].to(dev) == labels[b].to(dev)[vi, ui]) & ok
        n_ok, n_same = int(ok.sum()), int(same.sum())
        out.append({"a": int(a), "b": int(b), "agreement": (n_same / n_ok) if n_ok else None, "pixels": n_ok})
        tot_agree += n_same
        tot += n_ok
    return {"mean": (tot_agree / tot) if tot else None, "pixels": tot, "pairs": out}


# -- the stage on a run directory ---------------------------------------------------------------

@dataclass
class RunInfo:
    scene_dir: Path
    cameras: Cameras
    train_ids: list[int]
    test_ids: list[int]
    data: dict


def _read_run(scene_dir: Path) -> RunInfo:
    if not scene_dir.is_dir():
        raise InputError(f"{scene_dir}: run folder not found (run `ssgwarp reconstruct` first)")
    for f in ("scene.ply", "cameras.json"):
        if not (scene_dir / f).is_file():
            raise InputError(f"{scene_dir}: no {f} (run `ssgwarp reconstruct ... --out {scene_dir}` first)")
    cameras = Cameras.load(scene_dir / "cameras.json")
    data = read_json(scene_dir / "data.json") if (scene_dir / "data.json").is_file() else {}
    names = cameras.names
    index = {}
    for i, nm in enumerate(names):
        index.setdefault(nm, i)
        index.setdefault(Path(nm).stem, i)

    def ids_of(lst) -> list[int]:
        out = []
        for nm in lst or []:
            i = index.get(str(nm), index.get(Path(str(nm)).stem))
            if i is None:
                raise InputError(f"{scene_dir / 'data.json'}: split names image '{nm}' that cameras.json does not hold")
            out.append(i)
        return out

    split = data.get("split", {}) if isinstance(data, dict) else {}
    train = ids_of(split.get("train"))
    test = ids_of(split.get("test"))
    if not train:
        train = [i for i in range(len(cameras)) if i not in set(test)] or list(range(len(cameras)))
    return RunInfo(scene_dir, cameras, train, test, data if isinstance(data, dict) else {})


def _resolve_masks(masks: Optional[str | Path], run: RunInfo) -> Optional[Path]:
    """``None``/"none" → mask-free; "auto" → ``RUN/object_mask`` (``ssgwarp masks``), else
    ``<data_dir>/object_mask``, when it exists; else the folder given."""
    if masks is None or str(masks).lower() == "none":
        return None
    if str(masks).lower() == "auto":
        dd = run.data.get("data_dir")
        for cand in (run.scene_dir / "object_mask", Path(dd) / "object_mask" if dd else None):
            if cand is not None and cand.is_dir():
                return cand
        return None
    return Path(masks)


def _train_images(scene_dir: Path, run: RunInfo, device) -> Optional[Tensor]:
    """The run's training images ``[T, H, W, 3]`` (reloaded from its capture), or None when the capture
    cannot be read (the mask-free path then clusters on the Gaussians' own colours, and says so)."""
    from .datasets import load_run

    try:
        _, data = load_run(scene_dir)
    except (InputError, OSError):
        return None
    if data.cameras.names != run.cameras.names:
        return None
    return data.images[run.train_ids].to(device)


def _coverage(labels: Tensor, k: int) -> list[float]:
    cnt = torch.bincount(labels.flatten().cpu().long(), minlength=k).double()
    return (cnt / cnt.sum().clamp_min(1)).tolist()


def _plot(path: Path, criterion: Optional[dict], history: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_crit = bool(criterion and criterion.get("values"))
    fig, axes = plt.subplots(1, 2 if has_crit else 1, figsize=(10 if has_crit else 5, 3.6))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    if history:
        st = [h["step"] for h in history]
        ax.plot(st, [h["ce"] for h in history], label="cross entropy / log K")
        regs = [(h["step"], h["reg"]) for h in history if h.get("reg")]
        if regs:
            ax.plot(*zip(*regs), label="3D KL / K")
        ax.set_yscale("log")
        ax.legend()
    ax.set_xlabel("step")
    ax.set_title("training loss")
    if has_crit:
        ks = sorted(int(k) for k in criterion["values"])
        vals = [criterion["values"][k] if k in criterion["values"] else criterion["values"][str(k)] for k in ks]
        ax2 = axes[1]
        ax2.plot(ks, vals, "o-")
        ax2.axvline(criterion.get("chosen_k", ks[0]), color="gray", ls="--", label=f"chosen K={criterion.get('chosen_k')}")
        ax2.set_xlabel("K")
        ax2.set_ylabel("log-eigengap")
        ax2.set_title(f"K criterion (final K={criterion.get('final_k')})")
        ax2.legend()
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp"}


def map_name(name: str) -> str:
    """File stem of a camera's group map: the image name without its image extension, '/' → '_'."""
    p = Path(name)
    base = p.with_suffix("") if p.suffix.lower() in _IMAGE_SUFFIXES else p
    return base.as_posix().replace("/", "_")


def write_group_outputs(scene_dir: Path, scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear,
                        info: dict, *, history: Sequence[dict] = (), progress: bool = True) -> tuple[dict, Tensor]:
    """Write scene.ply (with identities), groups/classifier.pt, groups/groups.json, group maps and the plot.

    Returns the completed ``info`` (per-group Gaussian counts and coverage added)
    and the group maps ``[C, H, W]`` (int16, CPU) of ``cameras``.
    """
    from .palette import colorize_labels
    from .ply import write_ply

    k = classifier.out_features
    gdir = scene_dir / "groups"
    labels = group_labels(scene, cameras, classifier, progress=progress)
    ids, prob = gaussian_groups(scene, classifier)
    counts = torch.bincount(ids.cpu(), minlength=k).tolist()
    train_ids = info.get("train_ids", list(range(len(cameras))))
    cover_train = _coverage(labels[train_ids], k) if train_ids else _coverage(labels, k)
    info["groups"] = [{"id": g, "gaussians": int(counts[g]), "screen_coverage": float(cover_train[g]),
                       "mean_probability": float(prob[ids == g].mean()) if counts[g] else None}
                      for g in range(k)]
    info["groups_present"] = int(sum(1 for g in info["groups"] if g["gaussians"] > 0 or g["screen_coverage"] > 0))
    write_ply(scene_dir / "scene.ply", scene.detach().to("cpu"))
    with atomic_path(gdir / "classifier.pt") as tmp:
        torch.save({"format": FORMAT, "dim": classifier.in_features, "num_groups": k,
                    "state_dict": {n: t.detach().cpu() for n, t in classifier.state_dict().items()}}, tmp)
    for i, name in enumerate(cameras.names):
        write_image(gdir / "group_maps" / f"{map_name(name)}.png",
                    colorize_labels(labels[i], k))
    info["outputs"] = {"classifier": "groups/classifier.pt", "group_maps": "groups/group_maps/",
                       "plot": "groups/groups.png", "scene": "scene.ply"}
    write_json(gdir / "groups.json", info)
    _plot(gdir / "groups.png", info.get("criterion"), list(history),
          f"{scene_dir.name}: K={k} ({str(info.get('method')).split(' (')[0]})")
    return info, labels


def group_scene(scene_dir: str | Path, *, masks: Optional[str | Path] = "auto", num_groups: Optional[int] = None,
                max_groups: int = 8, joint: bool = False, config: GroupConfig = GroupConfig(),
                cluster: Optional[ClusterConfig] = None, ignore_id: Optional[int] = None, force: bool = False,
                resume: bool = False, device=None, seed: int = 0, progress: bool = True,
                reconstruct_kwargs: Optional[dict] = None) -> dict:
    """Group a reconstructed run (what ``ssgwarp group`` runs); returns the groups.json content.

    ``masks``: a folder of instance masks, "auto" (``<data_dir>/object_mask``
    when present, else mask-free) or None/"none" (mask-free).
    """
    from .pseudomasks import pseudo_masks
    from .ply import read_ply

    t0 = time.time()
    scene_dir = Path(scene_dir)
    run = _read_run(scene_dir)
    gdir = scene_dir / "groups"
    if (gdir / "groups.json").is_file() and not force and not resume:
        raise SsgwarpError(f"{scene_dir} is already grouped ({gdir / 'groups.json'}); use --force to group it again")
    if num_groups is not None and num_groups < 1:
        raise InputError(f"--groups must be >= 1, got {num_groups}")
    if max_groups < 1:
        raise InputError(f"--max-groups must be >= 1, got {max_groups}")
    if config.dim < 1:
        raise InputError(f"--dim must be >= 1, got {config.dim}")
    device = torch.device(device) if device is not None else torch.device("cpu")
    scene = read_ply(scene_dir / "scene.ply", device=device)
    scene = scene.replace(identities=None)
    cams = run.cameras
    train_cams = cams[run.train_ids]
    mask_dir = _resolve_masks(masks, run)
    info: dict = {"format": FORMAT, "dim": config.dim, "seed": int(seed), "joint": bool(joint),
                  "train_ids": run.train_ids, "test_ids": run.test_ids,
                  "config": asdict(config)}
    if mask_dir is not None:
        from .masks import read_record

        made = read_record(mask_dir)        # written by `ssgwarp masks`: instances associated across views
        if made is not None and ignore_id is None:
            ignore_id = made.get("ignore_id")
        ms = load_masks(mask_dir, cams.names, cams.width, cams.height, num_groups=num_groups, ignore_id=ignore_id,
                        required=[i in set(run.train_ids) for i in range(len(cams))])
        k = ms.num_groups
        all_targets = ms.targets
        info.update({"method": "masks", "mask_dir": str(mask_dir), "mask_ids": ms.ids, "criterion": None,
                     "kind": KINDS["segmenter" if made and made.get("source", {}).get("kind") == "segmenter"
                                   else "masks"]})
        if made is not None:
            info["masks_record"] = {"source": made.get("source"), "num_instances": made.get("num_instances"),
                                    "ignore_id": made.get("ignore_id"), "record": str(mask_dir.parent / "masks.json")}
    else:
        ccfg = cluster if cluster is not None else ClusterConfig(max_groups=max_groups)
        if cluster is not None and cluster.max_groups != max_groups:
            ccfg = ClusterConfig(**{**asdict(cluster), "max_groups": max_groups})
        images = _train_images(scene_dir, run, device) if ccfg.colour == "images" else None
        masks_train, res = pseudo_masks(scene, train_cams, num_groups=num_groups, config=ccfg, seed=seed,
                                        images=images, progress=progress)
        k = res.num_groups
        all_targets = torch.full((len(cams), cams.height, cams.width), IGNORE, dtype=torch.long)
        all_targets[run.train_ids] = masks_train.cpu()
        crit = dict(res.criterion)
        crit["values"] = {int(a): float(b) for a, b in crit.get("values", {}).items()}
        info.update({"method": "mask-free (spectral clustering of the Gaussians on position, colour, shape; "
                               "K by log-eigengap)", "kind": KINDS["mask-free"],
                     "criterion": crit, "cluster_config": asdict(ccfg)})
    info["num_groups"] = k
    info["K"] = k
    history: list[dict] = []
    if joint:
        scene, classifier, extra = _joint(scene_dir, run, all_targets, k, config, seed, device, progress,
                                          reconstruct_kwargs or {}, resume=resume)
        info["joint_reconstruction"] = extra
    else:
        scene, classifier, history = train_identities(
            scene, train_cams, all_targets[run.train_ids], k, config=config, seed=seed, progress=progress,
            checkpoint_path=gdir / "checkpoint.pt", resume=resume)
    info["history_tail"] = history[-5:]
    info, labels = write_group_outputs(scene_dir, scene, cams, classifier, info, history=history, progress=progress)
    # how well the group maps reproduce the masks, and how well they agree across views
    tr = run.train_ids
    t = all_targets[tr]
    valid = t >= 0
    info["train_mask_accuracy"] = float((labels[tr].cpu()[valid] == t[valid]).double().mean()) if bool(valid.any()) else None
    if run.test_ids and mask_dir is not None:
        tt = all_targets[run.test_ids]
        v = tt >= 0
        info["test_mask_accuracy"] = float((labels[run.test_ids].cpu()[v] == tt[v]).double().mean()) if bool(v.any()) else None
    info["reprojection_agreement"] = reprojection_agreement(scene, cams, labels, neighbour_pairs(cams))
    info["seconds"] = round(time.time() - t0, 2)
    write_json(gdir / "groups.json", info)
    ck = gdir / "checkpoint.pt"
    if ck.is_file():
        ck.unlink()
    return info


def _joint(scene_dir: Path, run: RunInfo, targets: Tensor, k: int, config: GroupConfig, seed: int, device,
           progress: bool, kwargs: dict, resume: bool = False):
    """Re-run reconstruction of the run's capture with a :class:`GroupingHook` (replaces the run's scene).

    The capture is reloaded through :func:`ssgwarp.datasets.load_run`, so the
    Trainer's view indices are the rows of ``cameras.json`` (and of ``targets``).
    ``kwargs`` go to :func:`ssgwarp.reconstruct.reconstruct` (``iters``,
    ``sh_degree``, ``max_gaussians``, ``recipe``...); by default the original
    run's iteration count and SH degree are reused.
    """
    from . import reconstruct as rec
    from .datasets import load_run
    from .ply import read_ply

    _, data = load_run(scene_dir)
    if data.cameras.names != run.cameras.names:
        raise SsgwarpError(f"{scene_dir}: the reloaded capture's views do not match cameras.json")
    metrics = read_json(scene_dir / "metrics.json") if (scene_dir / "metrics.json").is_file() else {}
    kw = {"iters": int(metrics.get("iters", 30000)), "sh_degree": int(metrics.get("sh_degree", 3))}
    kw.update({k_: v for k_, v in kwargs.items() if v is not None})
    hook = GroupingHook(targets, k, config=config, seed=seed, device=device)
    metrics = rec.reconstruct(data.data_dir, scene_dir, hooks=[hook], identity_dim=config.dim, seed=seed,
                              device=device, progress=progress, data=data, force=not resume, resume=resume, **kw)
    scene = read_ply(scene_dir / "scene.ply", device=device)
    if scene.identities is None or scene.identities.shape[1] != config.dim:
        raise SsgwarpError("the joint reconstruction wrote no identity encodings of the expected length")
    summary = {"iters": metrics.get("iters"), "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"),
               "num_gaussians": metrics.get("num_gaussians"), "train_seconds": metrics.get("train_seconds")}
    return scene, hook.classifier.requires_grad_(False), summary


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


# -- CLI ------------------------------------------------------------------------------------------

def add_arguments(parser) -> None:
    parser.add_argument("scene_dir", type=Path, help="a reconstructed run (scene.ply, cameras.json, data.json)")
    parser.add_argument("--masks", default="auto",
                        help="folder of instance masks <image stem>.png (integer ids consistent across views); "
                             "'auto' (default): RUN/object_mask (from `ssgwarp masks`), else <data_dir>/object_mask, "
                             "when it exists, else mask-free; 'none': always mask-free")
    parser.add_argument("--groups", type=int, default=None, metavar="K",
                        help="number of groups (default: from the masks, or chosen per scene when mask-free)")
    parser.add_argument("--max-groups", type=int, default=8, metavar="CAP",
                        help="mask-free: the largest K considered (default 8)")
    parser.add_argument("--joint", action="store_true",
                        help="train identities jointly with a new reconstruction (re-runs reconstruct from data_dir)")
    parser.add_argument("--iters", type=int, default=None,
                        help=f"training steps (default {GroupConfig.iters} for the frozen-geometry stage; with "
                             "--joint: the reconstruction's own step count)")
    parser.add_argument("--dim", type=int, default=DEFAULT_DIM, metavar="E", help="identity length (default 16)")
    parser.add_argument("--reg-weight", type=float, default=GroupConfig.reg_weight,
                        help="weight of the 3D KL regulariser (0 = off)")
    parser.add_argument("--ignore-id", type=int, default=None,
                        help="a mask value meaning 'unlabelled' (those pixels are not trained on)")
    parser.add_argument("--resume", action="store_true", help="continue from groups/checkpoint.pt")
    parser.add_argument("--force", action="store_true", help="group again even if groups/ exists")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    if args.iters is not None and args.iters < 0:
        raise InputError(f"--iters must be >= 0, got {args.iters}")
    cfg = GroupConfig(dim=args.dim, reg_weight=args.reg_weight,
                      iters=args.iters if (args.iters is not None and not args.joint) else GroupConfig.iters)
    rk = {"iters": args.iters} if args.joint and args.iters is not None else None
    info = group_scene(args.scene_dir, masks=args.masks, num_groups=args.groups, max_groups=args.max_groups,
                       joint=args.joint, config=cfg, ignore_id=args.ignore_id, force=args.force,
                       resume=args.resume, device=args.device, seed=args.seed, progress=not args.quiet,
                       reconstruct_kwargs=rk)
    ra = info.get("reprojection_agreement", {}).get("mean")
    acc = info.get("train_mask_accuracy")
    print(f"grouped {args.scene_dir}: K={info['num_groups']} {info['kind']} ({info['method']}); "
          f"mask accuracy {acc if acc is None else f'{acc:.3f}'}; "
          f"cross-view agreement {ra if ra is None else f'{ra:.3f}'}; "
          f"wrote {Path(args.scene_dir) / 'groups'}")
    return 0
