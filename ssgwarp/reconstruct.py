"""3DGS reconstruction of a capture: ``ssgwarp reconstruct``.

The 3D Gaussian Splatting recipe (Kerbl et al. 2023), one view per step:

* loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)`` (:func:`ssgwarp.losses.photometric`);
* Adam (eps 1e-15), one parameter group per scene tensor with its own learning
  rate; the position rate decays exponentially from ``1.6e-4`` to ``1.6e-6``
  times the scene extent over the run;
* densification by a strategy (:mod:`ssgwarp.strategy`): ``"default"``, the 3DGS
  rules (clone / split by the view-space positional gradient in NDC units, prune
  by opacity and size, opacity reset; at most ``max_gaussians`` Gaussians), or
  ``"mcmc"``, 3DGS-MCMC (relocation of dead Gaussians, growth up to the budget
  ``max_gaussians``, opacity-gated position noise, opacity and scale
  regularisers); its schedule scales with the run's length;
* SH degree raised by one every ``sh_interval`` steps up to ``sh_degree``.

Densification works on every tensor the scene holds (identity encodings
included) and its Adam state, so Gaussian Grouping can train jointly through ``hooks``.

Runs are seeded and repeatable (views, split samples and initial identities
come from dedicated generators), checkpoint atomically to ``OUT/checkpoint.pt``
every ``checkpoint_every`` steps and on Ctrl-C, and resume bit-exactly
(``--resume``). A NaN loss stops the run with the step number; the last good
checkpoint is kept.
"""
from __future__ import annotations

import logging
import math
import random
import shutil
import signal
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from .cameras import Cameras
from .errors import InputError, SsgwarpError
from .scene import GaussianScene

log = logging.getLogger("ssgwarp.reconstruct")

CHECKPOINT_FORMAT = "ssgwarp-reconstruct-checkpoint/1"
OUTPUTS = ("scene.ply", "cameras.json", "data.json", "metrics.json")


BATCH_SCALINGS = ("sqrt", "linear", "none")
_STEP_FIELDS = ("sh_interval", "refine_start", "refine_stop", "refine_every", "reset_every")


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


@dataclass
class Recipe:
    """Training knobs; defaults are the 3DGS paper's (3DGS-MCMC's where the strategy says so).

    Step counts are absolute. Fields left None are resolved for the run by :meth:`resolved`:
    ``sh_interval`` is ``min(1000, iters // (2 * sh_degree))`` so short runs still reach their
    degree; the refine schedule (``refine_start``, ``refine_stop``, ``refine_every``,
    ``reset_every``) is the strategy's reference schedule at 30,000 steps scaled to ``iters``
    (:func:`ssgwarp.strategy.scaled_schedule`); ``init_opacity``, ``init_scale``,
    ``opacity_reg`` and ``scale_reg`` are the strategy's (default: 0.1, 1, 0, 0, the scale
    thinned for a dense cloud of random points by :func:`ssgwarp.strategy.random_init_scale`;
    mcmc: 0.5, 0.1, 0.01, 0.01).
    """

    lr_means: float = 1.6e-4           # times the scene extent
    lr_means_final: float = 1.6e-6     # times the scene extent, reached at the last step
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_identities: float = 2.5e-3
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2
    dssim_scale: float = 1.0           # multiplies the D-SSIM term; 0.5: the halved (1 - SSIM) / 2 of old runs
    sh_interval: Optional[int] = None
    # -- densification (ssgwarp.strategy) --
    refine_start: Optional[int] = None   # first refinement (30k reference: 500)
    refine_stop: Optional[int] = None    # no refinement from this step on (default 15000, mcmc 25000 at 30k)
    refine_every: Optional[int] = None   # steps between refinements (30k reference: 100; at least 10)
    reset_every: Optional[int] = None    # default: opacity reset interval (30k: 3000; at least 300); 0: none
    grad_threshold: float = 2e-4       # mean view-space positional gradient, NDC units (gsplat / INRIA)
    percent_dense: float = 0.01        # clone if max scale <= this x extent, else split
    split_factor: float = 1.6          # children scales = parent / split_factor
    prune_opacity: float = 0.005       # default: pruned below it; mcmc: dead (relocated) at or below it
    reset_opacity: float = 0.01
    prune_world: float = 0.1           # prune when max scale > this x extent (after the first reset)
    prune_screen: float = 0.0          # prune when the screen radius exceeded this fraction of max(W, H)
                                       # (after the first reset); 0: off
    mcmc_growth: float = 0.05          # mcmc: Gaussians added per refinement, fraction of the count
    noise_lr: float = 5e5              # mcmc: position noise scale (times the position learning rate)
    opacity_reg: Optional[float] = None  # weight of mean(opacity) in the loss
    scale_reg: Optional[float] = None    # weight of mean(scale / extent) in the loss
    init_opacity: Optional[float] = None
    init_scale: Optional[float] = None   # initial scale: this x the mean distance to the 3 nearest points
    init_max_points: Optional[int] = None  # subsample the initial points (None: all)
    identity_init_std: float = 0.1
    # -- batches of views (--batch-size B) --
    batch_scaling: str = "sqrt"        # Adam for B views per step: "sqrt" (learning rates x sqrt(B)),
                                       # "linear" (x B), both with betas ** B; "none": B=1's lrs and betas

    def resolved(self, iters: int, sh_degree: int, strategy="default", random_init: Optional[int] = None,
                 batch_size: int = 1) -> "Recipe":
        """The recipe with every None field set for a run of ``iters`` steps of ``batch_size`` views
        with ``strategy`` (``random_init``: the number of initial points when they are random, not
        a point cloud).

        Defaults are set for the run's number of images (``iters * batch_size``) and then counted
        in steps (divided by ``batch_size``): a batch run refines, resets opacities and raises the
        SH degree after the same number of images as a one-view run. Values given are steps."""
        from .strategy import make_strategy

        if self.batch_scaling not in BATCH_SCALINGS:
            raise InputError(f"Recipe.batch_scaling {self.batch_scaling!r}: choose one of {', '.join(BATCH_SCALINGS)}")
        b = max(1, int(batch_size))
        images = iters * b
        r = self
        fill = {}
        if r.sh_interval is None:
            fill["sh_interval"] = max(1, min(1000, images // (2 * max(1, sh_degree))))
        fill.update({k: v for k, v in make_strategy(strategy).defaults(images, random_init).items()
                     if getattr(r, k) is None})
        for k in _STEP_FIELDS:  # images -> steps
            if fill.get(k):
                fill[k] = max(1, round(fill[k] / b))
        r = replace(r, **fill)
        if r.reset_every is None:
            r = replace(r, reset_every=0)
        for k in ("refine_every", "sh_interval"):
            if getattr(r, k) < 1:
                raise InputError(f"Recipe.{k} must be >= 1, got {getattr(r, k)}")
        if r.reset_every < 0 or r.refine_start < 0:
            raise InputError("Recipe.reset_every and Recipe.refine_start must be >= 0")
        return r


# ----------------------------------------------------------------------------- rendering
def render_views(scene: GaussianScene, cameras: Cameras, *, sh_degree: int, identities: bool = False,
                 backgrounds: Optional[torch.Tensor] = None, rasterize: Optional[Callable] = None, **kwargs):
    """Render ``scene`` from ``cameras`` with a gsplat-compatible ``rasterize`` function.

    Without identities the SH evaluation is left to the rasterizer (``sh_degree``);
    with them, colours are evaluated here and the identity channels appended
    (one blending pass). Returns ``(colors [C,H,W,D], alphas [C,H,W,1], meta)``.
    """
    if rasterize is None:
        from .rasterize import rasterization as rasterize
    C = len(cameras)
    viewmats = cameras.viewmats.to(scene.dtype)
    Ks = cameras.Ks.to(scene.dtype)
    deg = min(sh_degree, scene.sh_degree)
    if not identities:
        coeffs = scene.sh_coeffs[:, : (deg + 1) ** 2]
        return rasterize(scene.means, scene.quats, scene.scales, scene.opacities, coeffs, viewmats, Ks,
                         cameras.width, cameras.height, sh_degree=deg, backgrounds=backgrounds, **kwargs)
    from .sh import spherical_harmonics
    from .scene import sh_dc_to_rgb

    if deg == 0:
        rgb = sh_dc_to_rgb(scene.sh_dc).clamp_min(0.0)[None].expand(C, -1, -1)
    else:
        dirs = scene.means[None] - cameras.centers.to(scene.dtype)[:, None]
        coeffs = scene.sh_coeffs[:, : (deg + 1) ** 2]
        rgb = (spherical_harmonics(deg, dirs, coeffs[None].expand(C, -1, -1, -1)) + 0.5).clamp_min(0.0)
    colors = torch.cat([rgb, scene.identities[None].expand(C, -1, -1)], dim=-1)
    return rasterize(scene.means, scene.quats, scene.scales, scene.opacities, colors, viewmats, Ks,
                     cameras.width, cameras.height, backgrounds=backgrounds, **kwargs)


# ----------------------------------------------------------------------------- trainer
class Trainer:
    """The 3DGS training loop on one :class:`~ssgwarp.datasets.SceneData`.

    Args:
        data: the capture (its ``train_ids`` are trained on, ``test_ids`` evaluated).
        scene: initial scene (default: from ``data.points``).
        iters: total number of steps.
        sh_degree: final SH degree (0..3).
        max_gaussians: cap on the number of Gaussians (the budget of the mcmc strategy).
        recipe: :class:`Recipe`.
        strategy: ``"default"`` or ``"mcmc"`` (or a :class:`ssgwarp.strategy.Strategy`).
        hooks: objects with ``parameters() -> list[param-group dicts]`` and
            ``loss(step, view_index, identity_render [H,W,E]) -> Tensor``. When a hook
            is present and the scene has identities, identities are rendered in the
            same pass as colour, optimised (``recipe.lr_identities``) and densified,
            and each hook's loss is added. A hook with a ``scene_fn`` attribute gets
            a callable returning the current scene. ``view_index`` indexes ``data``.
        identity_dim: give the initial scene identity encodings of this size (random,
            ``recipe.identity_init_std``) when it has none.
        checkpoint_path: where checkpoints go (None: no checkpoints).
        checkpoint_every: steps between checkpoints.
        rasterize: a gsplat-compatible rasterization function (default ssgwarp's).
        raster_kwargs: extra keyword arguments for it.
        batch_size: training views per step, over all processes (default: one per process). The
            loss is their mean; Adam is adapted by ``recipe.batch_scaling`` (:func:`batch_factors`)
            and the default schedule counts images (:meth:`Recipe.resolved`).
        group: a :class:`ssgwarp.distributed.Group` when several processes train together (each
            renders its share of every batch); default: alone.
        device, seed, progress: as usual.
    """

    def __init__(self, data, *, scene: Optional[GaussianScene] = None, iters: int = 30000, sh_degree: int = 3,
                 max_gaussians: int = 1_000_000, recipe: Optional[Recipe] = None, hooks: Sequence = (),
                 identity_dim: Optional[int] = None, checkpoint_path: Optional[str | Path] = None,
                 checkpoint_every: int = 500, rasterize: Optional[Callable] = None,
                 raster_kwargs: Optional[dict] = None, device=None, seed: int = 0, progress: bool = True,
                 strategy="default", batch_size: Optional[int] = None, group=None):
        from .distributed import SINGLE
        from .strategy import make_strategy

        if iters < 1:
            raise InputError(f"iters must be >= 1, got {iters}")
        if not 0 <= sh_degree <= 3:
            raise InputError(f"sh_degree must be 0..3, got {sh_degree}")
        if max_gaussians < 1:
            raise InputError(f"max_gaussians must be >= 1, got {max_gaussians}")
        if not data.train_ids:
            raise InputError("no training views")
        self.group = group if group is not None else SINGLE
        self.batch_size = int(batch_size) if batch_size is not None else self.group.world_size
        if self.batch_size < 1:
            raise InputError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.batch_size % self.group.world_size:
            raise InputError(f"--batch-size {self.batch_size} cannot be split evenly between "
                             f"{self.group.world_size} processes; use a multiple of {self.group.world_size}")
        self.device = torch.device(device) if device is not None else data.device
        self.data = data.to(self.device)
        self.iters = int(iters)
        self.sh_degree = int(sh_degree)
        self.max_gaussians = int(max_gaussians)
        self.strategy = make_strategy(strategy)
        recipe = recipe or Recipe()
        random_init = None
        if scene is None and getattr(data, "points_source", "") == "random" and data.points is not None:
            random_init = self._initial_count(len(data.points[0]), recipe)
        self.recipe = recipe.resolved(self.iters, self.sh_degree, self.strategy, random_init, self.batch_size)
        self.lr_factor, self.beta_power = batch_factors(self.batch_size, self.recipe.batch_scaling)
        self.hooks = list(hooks)
        self.checkpoint_path = Path(checkpoint_path) if checkpoint_path is not None else None
        self.checkpoint_every = int(checkpoint_every)
        self.rasterize = rasterize
        self.raster_kwargs = dict(raster_kwargs or {})
        if rasterize is None:
            self.raster_kwargs.setdefault("validate", False)  # the loss is checked for NaN every step
        self.seed = int(seed)
        self.progress = progress and self.group.is_main
        self.extent = float(self.data.extent)
        self.step = 0
        self.elapsed = 0.0
        self.last_checkpoint_step: Optional[int] = None
        self._stop = False
        self._agreed_stop = False  # the stop request as all processes agreed on it (in the gradient all-reduce)
        from .distributed import check_every
        self.check_every = check_every() if self.group.active else 0
        self.history: list[dict] = []

        self.view_gen = torch.Generator().manual_seed(self.seed)
        self._queue: list[int] = []
        self._bg: dict[int, torch.Tensor] = {}

        if scene is None:
            scene = self._initial_scene()
        if scene.sh_degree != self.sh_degree:
            scene = scene.with_sh_degree(self.sh_degree)
        if identity_dim and scene.identities is None:
            g = torch.Generator().manual_seed(self.seed + 2)
            ids = torch.randn(len(scene), int(identity_dim), generator=g) * self.recipe.identity_init_std
            scene = scene.replace(identities=ids.to(scene.device, scene.dtype))
        scene = scene.to(self.device, torch.float32)
        if self.strategy.budgeted and len(scene) > self.max_gaussians:
            raise InputError(f"the initial scene has {len(scene)} Gaussians, more than the budget of "
                             f"{self.max_gaussians} (--max-gaussians) of the {self.strategy.name} strategy")
        if self.hooks and scene.identities is None:
            log.warning("hooks given but the scene has no identity encodings (pass identity_dim): "
                        "their losses are not used")
        self._build_optimizer(scene)
        self.strategy.setup(self.gaussians, recipe=self.recipe, extent=self.extent,
                            max_gaussians=self.max_gaussians, seed=self.seed)
        for h in self.hooks:
            if hasattr(h, "scene_fn"):
                h.scene_fn = lambda: self.scene

    # -- state --------------------------------------------------------------------------------
    def _initial_scene(self) -> GaussianScene:
        if self.data.points is None:
            raise InputError("the capture has no initial points (and none were generated); pass a scene")
        xyz, rgb = self.data.points
        xyz, rgb = xyz.float().cpu(), rgb.float().cpu()
        m = self._initial_count(len(xyz), self.recipe)
        if len(xyz) > m:
            g = torch.Generator().manual_seed(self.seed + 3)
            idx = torch.randperm(len(xyz), generator=g)[:m].sort().values
            xyz, rgb = xyz[idx], rgb[idx]
        if len(xyz) == 0:
            raise InputError("the capture has an empty point cloud")
        from .scene import knn_mean_distance

        xyz = xyz.to(self.device)
        scale = knn_mean_distance(xyz, k=3).clamp_min(1e-7) * self.recipe.init_scale
        return GaussianScene.from_points(xyz, rgb.to(self.device), sh_degree=0,
                                         opacity=self.recipe.init_opacity, scale=scale)

    def _initial_count(self, n: int, recipe: Recipe) -> int:
        """How many of ``n`` capture points start the scene (``init_max_points``; the budget of a budgeted strategy)."""
        if recipe.init_max_points is not None:
            n = min(n, recipe.init_max_points)
        return min(n, self.max_gaussians) if self.strategy.budgeted else n

    def _lr(self, name: str) -> float:
        """Learning rate of scene tensor ``name`` for this run's batch size (at step 0)."""
        r = self.recipe
        return self.lr_factor * {"means": r.lr_means * self.extent, "log_scales": r.lr_scales,
                                 "quats": r.lr_quats, "logit_opacities": r.lr_opacity, "sh_dc": r.lr_sh_dc,
                                 "sh_rest": r.lr_sh_rest, "identities": r.lr_identities}[name]

    @property
    def betas(self) -> tuple[float, float]:
        """Adam's betas for this run's batch size (0.9, 0.999 raised to :attr:`beta_power`)."""
        return 0.9 ** self.beta_power, 0.999 ** self.beta_power

    def _build_optimizer(self, scene: GaussianScene) -> None:
        from .strategy import GaussianParams

        params = {k: torch.nn.Parameter(v.detach().clone().contiguous()) for k, v in scene.tensors().items()}
        groups = [{"params": [p], "lr": self._lr(k), "name": k} for k, p in params.items()]
        self.gaussians = GaussianParams(params, torch.optim.Adam(groups, eps=self.recipe.adam_eps, betas=self.betas))
        hook_groups = []
        for h in self.hooks:
            hook_groups.extend(h.parameters())
        self.hook_opt = torch.optim.Adam(hook_groups, betas=self.betas) if hook_groups else None
        if self.hook_opt is not None and self.lr_factor != 1.0:
            for g in self.hook_opt.param_groups:
                g["lr"] *= self.lr_factor

    def _hook_params(self) -> list[torch.Tensor]:
        if self.hook_opt is None:
            return []
        return [p for g in self.hook_opt.param_groups for p in g["params"]]

    @property
    def params(self) -> dict[str, torch.nn.Parameter]:
        """The scene's tensors (live parameters), by :class:`GaussianScene` field name."""
        return self.gaussians.params

    @property
    def opt(self) -> torch.optim.Optimizer:
        return self.gaussians.opt

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def active_sh_degree(self) -> int:
        return min(self.sh_degree, self.step // max(1, self.recipe.sh_interval))

    @property
    def scene(self) -> GaussianScene:
        """The current scene (tensors are the live parameters)."""
        p = self.params
        return GaussianScene(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], p["sh_dc"],
                             p.get("sh_rest"), p.get("identities"), self.sh_degree)

    def final_scene(self) -> GaussianScene:
        """A detached copy of the scene."""
        return self.scene.detach()

    # -- training -------------------------------------------------------------------------------
    def _next_view(self) -> int:
        if not self._queue:
            ids = torch.as_tensor(self.data.train_ids)
            self._queue = ids[torch.randperm(len(ids), generator=self.view_gen)].tolist()
        return self._queue.pop()

    def next_batch(self) -> list[int]:
        """The next step's ``batch_size`` views (all processes draw the same; each renders its share).
        Consecutive batches are consecutive runs of the one-view order."""
        return [self._next_view() for _ in range(self.batch_size)]

    def _set_lrs(self) -> None:
        r = self.recipe
        t = min(1.0, self.step / max(1, self.iters))
        lr0, lr1 = r.lr_means * self.extent, r.lr_means_final * self.extent
        self.gaussians.groups["means"]["lr"] = self.lr_factor * math.exp(math.log(lr0) * (1 - t) + math.log(lr1) * t)

    def train_step(self) -> dict:
        """One optimisation step (``self.step`` counts completed steps)."""
        from .losses import photometric

        r = self.recipe
        views = self.group.share(self.next_batch())  # this process's views of the step's batch
        self._set_lrs()
        cam = self.data.cameras[views]
        gt = torch.stack([self.data.images[v] for v in views])
        scene = self.scene
        with_ids = bool(self.hooks) and scene.identities is not None
        ch = 3 + (scene.identities.shape[1] if with_ids else 0)
        bg = self._bg.get(ch)
        if bg is None:
            bg = self._bg[ch] = self.data.background_tensor(ch)[None].expand(len(views), -1).contiguous()
        try:
            out, alphas, meta = render_views(scene, cam, sh_degree=self.active_sh_degree, identities=with_ids,
                                             backgrounds=bg, rasterize=self.rasterize, **self.raster_kwargs)
        except ValueError as e:
            if "NaN" in str(e) or "Inf" in str(e):
                self._diverged(str(e))
            raise
        means2d = meta["means2d"]
        if self.strategy.uses_means2d_grad and means2d.requires_grad:
            means2d.retain_grad()
        img = out[..., :3]
        loss = photometric(img, gt, r.lambda_dssim, r.dssim_scale)  # (the mean over the views)
        reg = self.strategy.regularizer(self.gaussians)
        if reg is not None:
            loss = loss + reg
        hook_losses = []
        if with_ids:
            for h in self.hooks:
                per_view = [h.loss(self.step, vi, out[j, ..., 3:]) for j, vi in enumerate(views)]
                hook_losses.append(sum(per_view) / len(per_view))
        total = loss + sum(hook_losses) if hook_losses else loss
        finite = bool(torch.isfinite(total))
        if not finite and not self.group.active:
            self._diverged("the loss is NaN/inf")
        total.backward()
        # every process steps with the batch's mean gradient; NaN and Ctrl-C anywhere are seen everywhere
        bad, stop = self.group.average_grads(list(self.params.values()) + self._hook_params(),
                                             [0.0 if finite else 1.0, 1.0 if self._stop else 0.0])
        self._agreed_stop = stop > 0
        if bad > 0:
            self._diverged("the loss is NaN/inf" + ("" if not self.group.active else
                                                    f" on {int(bad)} of {self.group.world_size} processes"))
        self._observe(meta)
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        if self.hook_opt is not None:
            self.hook_opt.step()
            self.hook_opt.zero_grad(set_to_none=True)
        self.step += 1
        info = {"loss": total.detach(), "mse": ((img.detach().clamp(0, 1) - gt) ** 2).mean()}
        info.update(self.strategy.step(self.gaussians, self.step, self.gaussians.groups["means"]["lr"]))
        if self.check_every and self.step % self.check_every == 0:
            self.group.check_identical(self._synced_tensors(), self.step)
        return info

    def _observe(self, meta: dict) -> None:
        """The strategy's statistics of this step's views, from every process's share."""
        g = self.gaussians
        if not self.group.active or not g.stats:
            self.strategy.observe(g, meta)
            return
        kept = g.stats
        g.stats = {k: torch.zeros_like(v) for k, v in kept.items()}
        self.strategy.observe(g, meta)
        ops = self.strategy.stat_ops
        self.group.reduce_stats(g.stats, ops)
        g.stats = {k: (torch.maximum(kept[k], v) if ops.get(k, "sum") == "max" else kept[k] + v)
                   for k, v in g.stats.items()}

    def _synced_tensors(self) -> dict[str, torch.Tensor]:
        """What every process must hold identically: parameters, Adam moments, statistics."""
        out = {f"param.{k}": v for k, v in self.params.items()}
        for k, p in self.params.items():
            out.update({f"adam.{k}.{n}": v for n, v in self.gaussians._moments(p).items()})
        out.update({f"stat.{k}": v for k, v in self.gaussians.stats.items()})
        out.update({f"hook.{i}": p for i, p in enumerate(self._hook_params())})
        return out

    def _diverged(self, why: str) -> None:
        where = (f"the last good checkpoint (step {self.last_checkpoint_step}) is kept at {self.checkpoint_path}"
                 if self.last_checkpoint_step is not None else "no checkpoint was written yet")
        raise SsgwarpError(f"training diverged at step {self.step + 1} ({why}); {where}; try a lower learning "
                           f"rate, another --seed, or --resume from the checkpoint")

    def train(self, until: Optional[int] = None) -> GaussianScene:
        """Train up to step ``until`` (default ``iters``); checkpoints on the way and on Ctrl-C."""
        from tqdm import tqdm

        until = self.iters if until is None else min(int(until), self.iters)
        old_handlers = {}
        if threading.current_thread() is threading.main_thread():
            def on_sigint(signum, frame):
                # second Ctrl-C: stop now (alone; with several processes torchrun forwards the first
                # Ctrl-C as a second one and stops the others with SIGTERM: all finish the step together)
                if self._stop and not self.group.active:
                    raise KeyboardInterrupt
                self._stop = True
            old_handlers[signal.SIGINT] = signal.signal(signal.SIGINT, on_sigint)
            if self.group.active:
                old_handlers[signal.SIGTERM] = signal.signal(signal.SIGTERM, on_sigint)
        bar = tqdm(total=until, initial=self.step, desc="reconstruct", unit="step", disable=not self.progress,
                   dynamic_ncols=True)
        t0 = time.time() - self.elapsed
        ema_psnr = None
        clean = False
        try:
            while self.step < until:
                info = self.train_step()
                self.elapsed = time.time() - t0
                bar.update(1)
                if self.step % 10 == 0 or self.step == until:
                    mse = float(info["mse"])
                    p = -10.0 * math.log10(max(mse, 1e-10))
                    ema_psnr = p if ema_psnr is None else 0.9 * ema_psnr + 0.1 * p
                    bar.set_postfix(loss=f"{float(info['loss']):.4f}", psnr=f"{ema_psnr:.2f}",
                                    gaussians=self.num_gaussians, sh=self.active_sh_degree, refresh=False)
                    self.history.append({"step": self.step, "loss": float(info["loss"]), "psnr": p,
                                         "gaussians": self.num_gaussians})
                if self.checkpoint_path is not None and self.checkpoint_every > 0 \
                        and self.step % self.checkpoint_every == 0:
                    self.save_checkpoint()
                if self._agreed_stop if self.group.active else self._stop:
                    # Ctrl-C arrived during this step (on any process): it finished cleanly, save it
                    self.elapsed = time.time() - t0
                    if self.checkpoint_path is not None:
                        self.save_checkpoint()
                        if self.group.is_main:
                            log.warning("interrupted at step %d; checkpoint saved to %s (rerun with --resume)",
                                        self.step, self.checkpoint_path)
                    self.group.barrier()  # nobody leaves before the checkpoint is written
                    clean = True
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            if not clean:
                # stopped inside a step (second Ctrl-C): its state may be half-updated, keep the last checkpoint
                log.warning("interrupted inside step %d; the last checkpoint (step %s) is kept", self.step + 1,
                            self.last_checkpoint_step)
            raise
        finally:
            bar.close()
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
            self._stop = self._agreed_stop = False
        if self.checkpoint_path is not None and self.last_checkpoint_step != self.step:
            self.save_checkpoint()
        return self.final_scene()

    # -- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        npst = np.random.get_state()
        rng = {"torch": torch.get_rng_state(),
               "numpy": [npst[0], torch.from_numpy(npst[1].astype(np.int64)), int(npst[2]), int(npst[3]),
                         float(npst[4])],
               "python": random.getstate(),
               "view": self.view_gen.get_state(), "split": self.strategy.generator_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "iters": self.iters,
            "sh_degree": self.sh_degree,
            "max_gaussians": self.max_gaussians,
            "seed": self.seed,
            "elapsed": self.elapsed,
            "recipe": asdict(self.recipe),
            "strategy": self.strategy.name,
            "batch_size": self.batch_size,
            "world_size": self.group.world_size,  # (informational: any number of processes resumes it)
            "names": list(self.data.names),
            "params": {k: v.detach().cpu() for k, v in self.params.items()},
            "optimizer": _to_cpu(self.opt.state_dict()),
            "hook_params": [p.detach().cpu() for p in self._hook_params()],
            "hook_optimizer": _to_cpu(self.hook_opt.state_dict()) if self.hook_opt is not None else None,
            "stats": {k: v.detach().cpu() for k, v in self.gaussians.stats.items()},
            "queue": list(self._queue),
            "rng": rng,
            "history": self.history[-1000:],
        }

    def save_checkpoint(self, path: Optional[str | Path] = None) -> Path:
        """Write the checkpoint (with several processes: the main one writes, the others only note the step)."""
        from .fileio import atomic_path

        path = Path(path) if path is not None else self.checkpoint_path
        if path is None:
            raise ValueError("no checkpoint path")
        if self.group.is_main:
            state = self.state_dict()
            with atomic_path(path) as tmp:
                torch.save(state, tmp)
        self.last_checkpoint_step = self.step
        return path

    def load_state_dict(self, st: dict) -> None:
        if st.get("format") != CHECKPOINT_FORMAT:
            raise InputError(f"not a reconstruction checkpoint (format {st.get('format')!r})")
        if list(st["names"]) != list(self.data.names):
            raise InputError("the checkpoint was trained on other images than this capture's "
                             "(different --images/--max-images?); use --force to start over")
        if int(st["sh_degree"]) != self.sh_degree:
            raise InputError(f"the checkpoint has SH degree {st['sh_degree']}, not {self.sh_degree}; "
                             f"pass --sh-degree {st['sh_degree']} to resume it")
        kind = st.get("strategy", "default")
        if kind != self.strategy.name:
            raise InputError(f"the checkpoint was trained with --strategy {kind}, not {self.strategy.name}; "
                             f"pass --strategy {kind} to resume it")
        b = int(st.get("batch_size", 1))
        if b != self.batch_size:
            raise InputError(f"the checkpoint was trained with --batch-size {b}, not {self.batch_size}; "
                             f"pass --batch-size {b} to resume it (with any number of processes dividing it)")
        saved = set(st["params"])
        if saved != set(self.params):
            raise InputError(f"the checkpoint holds {sorted(saved)}, this run {sorted(self.params)}")
        scene = GaussianScene(**{k: v for k, v in st["params"].items()}, sh_degree=self.sh_degree)
        self._build_optimizer(scene.to(self.device))
        self.opt.load_state_dict(st["optimizer"])  # (new group dicts: GaussianParams looks them up by name)
        self.strategy.setup(self.gaussians, recipe=self.recipe, extent=self.extent,
                            max_gaussians=self.max_gaussians, seed=self.seed)
        # statistics this run keeps (a checkpoint may hold more, e.g. screen radii of a run that pruned by them)
        stats = {k: v.to(self.device) for k, v in st["stats"].items() if k in self.gaussians.stats}
        if set(stats) != set(self.gaussians.stats):
            raise InputError(f"the checkpoint's densification statistics ({sorted(stats)}) do not match this "
                             f"run's ({sorted(self.gaussians.stats)}): it was written with other densification "
                             f"settings; use --force to start over")
        self.gaussians.stats = stats
        hp = self._hook_params()
        if len(hp) != len(st["hook_params"]):
            raise InputError("the checkpoint's hook parameters do not match this run's hooks")
        with torch.no_grad():
            for p, v in zip(hp, st["hook_params"]):
                p.copy_(v.to(p.device))
        if self.hook_opt is not None and st["hook_optimizer"] is not None:
            self.hook_opt.load_state_dict(st["hook_optimizer"])
        self.step = int(st["step"])
        self.elapsed = float(st.get("elapsed", 0.0))
        self._queue = list(st["queue"])
        rng = st["rng"]
        torch.set_rng_state(rng["torch"])
        kind, keys, pos, has_gauss, cached = rng["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
        random.setstate(rng["python"])
        self.view_gen.set_state(rng["view"])
        self.strategy.set_generator_state(rng["split"])
        if "cuda" in rng and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(rng["cuda"])
        self.history = list(st.get("history", []))
        self.last_checkpoint_step = self.step

    def load_checkpoint(self, path: Optional[str | Path] = None, state: Optional[dict] = None) -> None:
        """Continue from the checkpoint at ``path`` (default: this run's), or from its already
        read ``state`` (:func:`read_checkpoint`)."""
        path = Path(path) if path is not None else self.checkpoint_path
        st = state if state is not None else read_checkpoint(path)
        try:
            self.load_state_dict(st)
        except KeyError as e:
            raise InputError(f"{path}: checkpoint lacks {e}; use --force to start over") from None
        log.info("resumed from %s at step %d", path, self.step)

    # -- evaluation -----------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, ids: Sequence[int]) -> torch.Tensor:
        """``[len(ids), H, W, 3]`` renders of the data's views ``ids`` at the final SH degree."""
        scene = self.scene.detach()
        out = []
        bg = self.data.background_tensor(3)[None]
        for i in ids:
            img, _, _ = render_views(scene, self.data.cameras[i], sh_degree=self.sh_degree, backgrounds=bg,
                                     rasterize=self.rasterize, **self.raster_kwargs)
            out.append(img[0, ..., :3].clamp(0.0, 1.0))
        return torch.stack(out) if out else torch.zeros(0, self.data.height, self.data.width, 3)

    @torch.no_grad()
    def evaluate(self, ids: Optional[Sequence[int]] = None, lpips=None) -> dict:
        """PSNR / SSIM (and LPIPS when a model is given) over the views ``ids`` (default: test views)."""
        from .losses import psnr, ssim

        ids = list(self.data.test_ids if ids is None else ids)
        per = []
        for i in ids:
            pred = self.render([i])
            gt = self.data.images[i][None]
            row = {"name": self.data.names[i], "psnr": float(psnr(pred, gt)), "ssim": float(ssim(pred, gt))}
            if lpips is not None:
                row["lpips"] = float(lpips(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2)).mean())
            per.append(row)
        out = {"views": len(per), "per_view": per}
        for k in ("psnr", "ssim", "lpips"):
            vals = [r[k] for r in per if k in r]
            out[k] = float(np.mean(vals)) if vals else None
        return out


def read_checkpoint(path: str | Path) -> dict:
    """The contents of a reconstruction checkpoint (on the CPU), or an :class:`InputError`."""
    try:
        st = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(f"{path}: unreadable checkpoint ({str(e).splitlines()[0] if str(e) else type(e).__name__});"
                         f" use --force to start over") from None
    if not isinstance(st, dict):
        raise InputError(f"{path}: not a reconstruction checkpoint")
    return st


def _to_cpu(obj):
    if torch.is_tensor(obj):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_to_cpu(v) for v in obj]
    return obj


# ----------------------------------------------------------------------------- the stage
def _lpips_model(device):
    """LPIPS (found, or downloaded where allowed: :mod:`ssgwarp.weights`), or ``(None, reason)``."""
    from .errors import WeightsNotFound
    from .metrics import load_lpips

    try:
        return load_lpips(device=device), None
    except WeightsNotFound as e:
        return None, f"skipped: {e}"
    except Exception as e:  # weights present but unusable: report, do not fail the run
        return None, f"skipped: LPIPS weights could not be loaded ({str(e).splitlines()[0] if str(e) else e})"


def reconstruct(data_dir: str | Path, out: str | Path, *, iters: int = 30000, images: str = "images",
                sh_degree: int = 3, max_gaussians: int = 1_000_000, resume: bool = False, force: bool = False,
                device=None, seed: int = 0, hooks: Sequence = (), identity_dim: Optional[int] = None,
                split_every: int = 8, width: Optional[int] = None, max_images: Optional[int] = None,
                background: Optional[Sequence[float]] = None, recipe: Optional[Recipe] = None,
                checkpoint_every: int = 500, num_random_points: int = 100_000,
                rasterize: Optional[Callable] = None, raster_kwargs: Optional[dict] = None,
                progress: bool = True, data=None, strategy="default", batch_size: Optional[int] = None,
                group=None) -> dict:
    """Reconstruct the capture in ``data_dir`` into the run folder ``out`` (what the CLI runs).

    Writes ``out/scene.ply``, ``cameras.json``, ``data.json``, ``metrics.json`` (and keeps
    ``out/checkpoint.pt``). Existing outputs are never overwritten unless ``force``
    (which starts over) or ``resume`` (which continues from the checkpoint).
    ``data`` may be a preloaded :class:`~ssgwarp.datasets.SceneData` of ``data_dir``.
    ``batch_size``: views per step over all processes (default: one per process; on
    ``resume``, the checkpoint's). ``group``: the :class:`ssgwarp.distributed.Group` of a
    data-parallel run (default: alone); only its main process writes files and evaluates.
    Returns the metrics dict (on the other processes: ``{}``).
    """
    from .distributed import SINGLE

    group = group if group is not None else SINGLE
    from .datasets import data_json, load_dataset
    from .fileio import write_json
    from .ply import write_ply

    out = Path(out).expanduser()
    device = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ckpt = out / "checkpoint.pt"
    existing = [f for f in OUTPUTS + ("checkpoint.pt",) if (out / f).exists()]
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    if existing and not (force or resume):
        raise SsgwarpError(f"{out} already holds a reconstruction ({', '.join(existing)}); pass --force to "
                           f"overwrite it or --resume to continue it")
    # load and validate everything before touching the output folder
    if data is None:
        kw = {} if background is None else {"background": background}
        data = load_dataset(data_dir, images=images, split_every=split_every, max_images=max_images, width=width,
                            num_random_points=num_random_points, seed=seed, **kw)
    state = read_checkpoint(ckpt) if resume and ckpt.is_file() and not force else None
    if state is not None and batch_size is None:
        batch_size = int(state.get("batch_size", 1))
    group.barrier()  # everyone has looked at OUT before the main process changes it
    trainer = Trainer(data, iters=iters, sh_degree=sh_degree, max_gaussians=max_gaussians, recipe=recipe,
                      hooks=hooks, identity_dim=identity_dim, checkpoint_path=ckpt,
                      checkpoint_every=checkpoint_every, rasterize=rasterize, raster_kwargs=raster_kwargs,
                      device=device, seed=seed, progress=progress, strategy=strategy, batch_size=batch_size,
                      group=group)
    if state is not None:
        trainer.load_checkpoint(ckpt, state=state)
        del state
        if trainer.step >= iters:
            log.info("the checkpoint is already at step %d: writing outputs only", trainer.step)
    elif resume and not force:
        if existing:
            raise SsgwarpError(f"{out}: nothing to resume (no checkpoint.pt); pass --force to start over")
        log.info("no checkpoint in %s: starting from scratch", out)
    if force and group.is_main:
        for f in existing:
            p = out / f
            p.unlink() if p.is_file() else shutil.rmtree(p)
    if group.is_main:
        out.mkdir(parents=True, exist_ok=True)
    group.barrier()

    if torch.cuda.is_available() and device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    trainer.train()
    peaks = None
    if group.active and device.type == "cuda":
        peaks = [round(v, 1) for v in group.gather(torch.cuda.max_memory_allocated(device) / 2**20)]
    if not group.is_main:
        return {}
    scene = trainer.final_scene()

    lpips, lpips_note = _lpips_model(device)
    ev = trainer.evaluate(lpips=lpips)
    metrics = {
        "psnr": ev["psnr"], "ssim": ev["ssim"], "lpips": ev["lpips"],
        "test_views": ev["views"],
        "num_gaussians": len(scene),
        "train_seconds": round(trainer.elapsed, 2),
        "iters": trainer.step,
        "sh_degree": scene.sh_degree,
        "identity_dim": None if scene.identities is None else int(scene.identities.shape[1]),
        "seed": seed,
        "device": str(device),
        "world_size": group.world_size,
        "batch_size": trainer.batch_size,
        "images_seen": trainer.step * trainer.batch_size,
        "batch_scaling": {"mode": trainer.recipe.batch_scaling, "lr_factor": trainer.lr_factor,
                          "betas": list(trainer.betas)},
        "resolution": [data.width, data.height],
        **data.metric_frame,
        "per_view": ev["per_view"],
    }
    r = trainer.recipe
    metrics["densification"] = {"strategy": trainer.strategy.name, "max_gaussians": trainer.max_gaussians,
                                "refine_start": r.refine_start, "refine_stop": r.refine_stop,
                                "refine_every": r.refine_every, "reset_every": r.reset_every}
    if ev["views"] == 0:
        metrics["note"] = "no held-out views (split_every=0 or a single image): PSNR/SSIM not measured"
    if lpips_note:
        metrics["lpips_note"] = lpips_note
    if device.type == "cuda" and torch.cuda.is_available():
        metrics["peak_gpu_memory_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
        if peaks is not None:  # every process's peak (they differ by their renders' workspace)
            metrics["peak_gpu_memory_mb_per_rank"] = peaks

    write_ply(out / "scene.ply", scene)
    data.cameras.to("cpu").save(out / "cameras.json")
    write_json(out / "data.json", data_json(data, seed=seed))
    write_json(out / "metrics.json", metrics)
    log.info("wrote %s: %d Gaussians, held-out PSNR %s", out, len(scene),
             "n/a" if metrics["psnr"] is None else f"{metrics['psnr']:.2f} dB")
    return metrics


# ----------------------------------------------------------------------------- CLI
def _background(s: str) -> tuple[float, float, float]:
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    if s in named:
        return named[s]
    try:
        v = tuple(float(x) for x in s.split(","))
    except ValueError:
        v = ()
    if len(v) != 3:
        raise InputError(f"--background {s!r}: expected white, black or R,G,B in [0, 1]")
    return v  # type: ignore[return-value]


def add_arguments(parser) -> None:
    parser.add_argument("data_dir", type=Path, help="the capture: COLMAP (sparse/0), LLFF (poses_bounds.npy) "
                        "or NeRF/instant-ngp (transforms*.json) folder")
    parser.add_argument("--out", type=Path, required=True, help="run folder to write")
    parser.add_argument("--iters", type=int, default=30000, help="training steps (default 30000; 7000 is a quick run)")
    parser.add_argument("--images", default="images", help="image sub-folder, e.g. images_4 or images_8 (default images)")
    parser.add_argument("--width", type=int, default=None, help="resize images to this width (default: as loaded)")
    parser.add_argument("--sh-degree", type=int, default=3, help="final SH degree 0..3 (default 3)")
    parser.add_argument("--strategy", choices=("default", "mcmc"), default="default",
                        help="densification: default (3DGS: clone/split/prune, opacity reset) or mcmc "
                             "(3DGS-MCMC: relocation, a fixed budget of --max-gaussians, position noise)")
    parser.add_argument("--max-gaussians", type=int, default=1_000_000,
                        help="cap on the number of Gaussians; with --strategy mcmc the budget it grows to "
                             "(default 1000000)")
    parser.add_argument("--split-every", type=int, default=8,
                        help="hold out every N-th image for testing (default 8, the LLFF convention; 0: none)")
    parser.add_argument("--max-images", type=int, default=None, help="use at most this many images (evenly spaced)")
    parser.add_argument("--background", type=_background, default=None,
                        help="white, black or R,G,B: what RGBA images are composited on (default white)")
    parser.add_argument("--random-points", type=int, default=100_000,
                        help="initial points when the capture has no point cloud (default 100000)")
    parser.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints (default 500)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="training views per step, over all processes (default: one per process; on "
                             "--resume the checkpoint's); the default schedule counts images, so --iters N "
                             "--batch-size B trains on N x B images (docs/scaling.md)")
    parser.add_argument("--batch-scaling", choices=("sqrt", "linear", "none"), default="sqrt",
                        help="Adam for batches: learning rates x sqrt(B) (default) or x B with betas ** B, "
                             "or none (one view's settings)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--force", action="store_true", help="overwrite an existing run in OUT")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    from . import distributed

    if args.resume and args.force:
        raise InputError("--resume and --force exclude each other")
    if args.batch_size is not None and args.batch_size < 1:
        raise InputError(f"--batch-size must be >= 1, got {args.batch_size}")
    group, device = distributed.from_env(args.device)  # under torchrun: join the others
    logging.basicConfig(level=logging.INFO if group.is_main else logging.WARNING, format="ssgwarp: %(message)s")
    try:
        m = reconstruct(args.data_dir, args.out, iters=args.iters, images=args.images, sh_degree=args.sh_degree,
                        max_gaussians=args.max_gaussians, resume=args.resume, force=args.force, device=device,
                        seed=args.seed, split_every=args.split_every, width=args.width, max_images=args.max_images,
                        background=args.background, checkpoint_every=args.checkpoint_every,
                        num_random_points=args.random_points, progress=not args.no_progress,
                        strategy=args.strategy, batch_size=args.batch_size,
                        recipe=Recipe(batch_scaling=args.batch_scaling), group=group)
    finally:
        distributed.shutdown(group)
    if not group.is_main:
        return 0
    ps = "n/a" if m["psnr"] is None else f"{m['psnr']:.2f} dB"
    ss = "n/a" if m["ssim"] is None else f"{m['ssim']:.4f}"
    print(f"{args.out}: {m['num_gaussians']} Gaussians, held-out PSNR {ps}, SSIM {ss}, "
          f"{m['train_seconds']:.0f} s")
    return 0
