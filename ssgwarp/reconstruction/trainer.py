"""The 3DGS training loop: :class:`Trainer` (one capture, a :class:`~ssgwarp.reconstruction.recipe.Recipe`, a
densification :class:`~ssgwarp.reconstruction.strategy.Strategy`, both set for the run by
:func:`~ssgwarp.reconstruction.recipe.resolve_run`, hooks such as Gaussian Grouping's, batches of views split over
processes by :mod:`ssgwarp.services.distributed`, their densification statistics combined by
:func:`~ssgwarp.reconstruction.statistics.observe_across`). Its state and checkpoint file are
:class:`~ssgwarp.reconstruction.checkpoint.TrainState`'s; the scores of the held-out views
:func:`ssgwarp.evaluation.held_out.score_views`'s (:meth:`Trainer.evaluate` renders them); the NaN check
:class:`~ssgwarp.reconstruction.step.LossWatch`'s; the initial scene :mod:`ssgwarp.reconstruction.initial`'s. Extensions: hooks (``hooks=``, or added while it runs with
:meth:`Trainer.add_hooks`, which ``attach=`` objects use, :mod:`ssgwarp.reconstruction.attach`).

Runs are seeded and repeatable (views, split samples and initial identities come from the run's
own generators), checkpoint atomically every ``checkpoint_every`` steps and on Ctrl-C, and resume
bit-exactly; a NaN loss stops the run with the step number, the last good checkpoint kept
(the policy of :mod:`ssgwarp.services.loop`). The command around it is :mod:`ssgwarp.reconstruction.reconstruct`.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from ..services.distributed import SINGLE, check_every
from ..errors import InputError
from ..core.optim import adam
from ..raster.adam_ops import warp_adam
from ..services.loop import Diverged, Loop, diverged_message
from ..services.losses import photometric
from ..core.optim import batch_factors
from .recipe import Recipe, resolve_run
from ..raster.rendering import render
from ..raster.scene import GaussianScene
from ..evaluation.held_out import masked
from .image_model import ImageModel
from .attach import attach_hooks, takes_scene
from .checkpoint import TrainState
from .initial import initial_scene
from .schedules import Schedules, sh_degree_at
from .statistics import observe_across
from .step import LossWatch, StepInfo, ViewCache, adam_step, zero_unrendered_grads
from .gaussians import GaussianParams
from .strategy import Strategy
from .pruning import ContributionPruning

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")


class Trainer(ImageModel):
    """The 3DGS training loop on one :class:`~ssgwarp.capture.datasets.SceneData`.

    Args:
        data: the capture (its ``train_ids`` are trained on, ``test_ids`` evaluated).
        scene: initial scene (default: from ``data.points``).
        iters: total number of steps, or ``"auto"`` (:mod:`.schedules`: until the training views' PSNR plateaus).
        recipe: :class:`Recipe` (the final SH degree included).
        strategy: a :class:`ssgwarp.reconstruction.strategy.Strategy` (its knobs: the cap ``max_gaussians``,
            the refine schedule, thresholds), or its name, ``"default"`` or ``"mcmc"``. The recipe and the
            strategy are resolved for the run by :func:`ssgwarp.reconstruction.recipe.resolve_run`
            (:attr:`recipe`, :attr:`strategy`: the resolved ones; the given ones are left as they are).
        hooks: objects with ``parameters() -> list[param-group dicts]`` and
            ``loss(step, view_index, identity_render [H,W,E]) -> Tensor``. When a hook
            is present and the scene has identities, identities are rendered in the
            same pass as colour, optimised (``recipe.lr_identities``) and densified,
            and each hook's loss is added. A hook whose ``loss`` takes a ``scene``
            parameter gets the current scene there (``loss(step, view_index,
            identity_render, scene=...)``). ``view_index`` indexes ``data``.
        identity_dim: give the initial scene identity encodings of this size (random,
            ``recipe.identity_init_std``) when it has none.
        checkpoint_path: where checkpoints go (None: no checkpoints).
        checkpoint_every: steps between checkpoints.
        rasterize: a gsplat-compatible rasterization function (default ssgwarp's).
        raster_kwargs: extra keyword arguments for it.
        batch_size: training views per step, over all processes (default: one per process). The
            loss is their mean; Adam is adapted by ``recipe.batch_scaling`` (:func:`batch_factors`)
            and the default schedule counts images (:func:`ssgwarp.reconstruction.recipe.resolve`).
        group: a :class:`ssgwarp.services.distributed.Group` when several processes train together (each
            renders its share of every batch); default: alone.
        backdrop: ``"auto"`` / ``"on"`` / ``"off"``: far points for the initial scene (:mod:`.backdrop`;
            :attr:`backdrop`: the decision, None when ``scene`` is given).
        attach: hooks made during the run (``reconstruct --groups``): :mod:`ssgwarp.reconstruction.attach`.
        appearance: ``"auto"`` / ``"on"`` / ``"off"``: per-image exposure and white balance
            (:mod:`.appearance`; :attr:`appearance_record`: the decision and its evidence).
        sky: ``"auto"`` / ``"on"`` / ``"off"``: an environment colour field behind the splats (:mod:`.sky`;
            :attr:`environment`, :attr:`sky_record`).
        device, seed, progress: as usual.
    """

    def __init__(self, data, *, scene: Optional[GaussianScene] = None, iters: int | str = 30000,
                 recipe: Optional[Recipe] = None, strategy: str | Strategy = "default", hooks: Sequence = (),
                 identity_dim: Optional[int] = None, checkpoint_path: Optional[str | Path] = None,
                 checkpoint_every: int = 500, rasterize: Optional[Callable] = None,
                 raster_kwargs: Optional[dict] = None, device=None, seed: int = 0, progress: bool = True,
                 batch_size: Optional[int] = None, group=None, backdrop: str = "auto",
                 attach=None, appearance: str = "auto", sky: str = "auto"):
        if not data.train_ids:
            raise InputError("no training views")
        self.group = group if group is not None else SINGLE
        self.batch_size = int(batch_size) if batch_size is not None else self.group.world_size
        if self.batch_size < 1:
            raise InputError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.batch_size % self.group.world_size:
            raise InputError(f"--batch-size {self.batch_size} cannot be split evenly between "
                             f"{self.group.world_size} processes; use a multiple of {self.group.world_size}")
        plan = resolve_run(data, recipe, strategy, iters, scene_given=scene is not None, batch_size=self.batch_size)
        self.iters, self.auto, self.recipe, self.strategy = plan.iters, plan.auto, plan.recipe, plan.strategy
        self.device = torch.device(device) if device is not None else data.device
        self.data = data.to(self.device)
        self.lr_factor, self.beta_power = batch_factors(self.batch_size, self.recipe.batch_scaling)
        self.schedules = Schedules(self.recipe, self.data, iters=self.iters, auto=self.auto,
                                   refine_stop=self.strategy.refine_stop)
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
        self._loop: Optional[Loop] = None
        self._agreed_stop = False  # the stop request as all processes agreed on it (in the gradient all-reduce)
        self._losses = LossWatch()   # the NaN check without a device synchronisation
        self.check_every = check_every() if self.group.active else 0
        self.history: list[dict] = []
        self.backdrop_mode, self.backdrop = backdrop, None
        self._init_image_model(appearance, sky)

        self.view_gen = torch.Generator().manual_seed(self.seed)
        self._queue: list[int] = []
        self._views = ViewCache(self.data)

        if scene is None:
            scene, self.backdrop = initial_scene(self.data, self.recipe, self.strategy,
                                                 backdrop_mode=self.backdrop_mode, seed=self.seed, device=self.device)
        if scene.sh_degree != self.sh_degree:
            scene = scene.with_sh_degree(self.sh_degree)
        if identity_dim and scene.identities is None:
            g = torch.Generator().manual_seed(self.seed + 2)
            ids = torch.randn(len(scene), int(identity_dim), generator=g) * self.recipe.identity_init_std
            scene = scene.replace(identities=ids.to(scene.device, scene.dtype))
        scene = scene.to(self.device, torch.float32)
        self._decide_image_model()  # (the sky from the layout, appearance auto from the points)
        if self.strategy.budgeted and len(scene) > self.max_gaussians:
            raise InputError(f"the initial scene has {len(scene)} Gaussians, more than the budget of "
                             f"{self.max_gaussians} (--max-gaussians) of the {self.strategy.name} strategy")
        if self.hooks and scene.identities is None:
            log.warning("hooks given but the scene has no identity encodings (pass identity_dim): "
                        "their losses are not used")
        self._build_optimizer(scene)
        self._setup_strategy()
        self.pruning = ContributionPruning.of(self.strategy)   # (None: off)
        self.attach, self._attached = attach, False
        if attach is not None:
            attach.prepare(self)

    # -- state --------------------------------------------------------------------------------
    def _setup_strategy(self) -> None:
        self.strategy.setup(self.gaussians, recipe=self.recipe, extent=self.extent, seed=self.seed)
        if self.backdrop is not None and self.backdrop.scene_radius:  # sizes beyond it measured by distance
            focal = float(self.data.cameras.Ks[list(self.data.train_ids), 0, 0].median())
            self.strategy.far_field(torch.tensor(self.backdrop.center, device=self.device), self.backdrop.scene_radius,
                                    focal)

    @property
    def sh_degree(self) -> int:
        """The final SH degree (the recipe's)."""
        return self.recipe.sh_degree

    @property
    def max_gaussians(self) -> int:
        """The cap on the number of Gaussians (the strategy's)."""
        return self.strategy.max_gaussians

    @property
    def finished(self) -> bool:
        """Whether the run reached its end: ``iters``, or where the stop rule ended it (``--iters auto``)."""
        return self.step >= self.schedules.end

    def learning_rate(self, name: str) -> float:
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
        params = {k: torch.nn.Parameter(v.detach().clone().contiguous()) for k, v in scene.tensors().items()}
        groups = [{"params": [p], "lr": self.learning_rate(k), "name": k} for k, p in params.items()]
        make = warp_adam if self.recipe.optimizer == "warp" else adam
        self.gaussians = GaussianParams(params, make(groups, eps=self.recipe.adam_eps, betas=self.betas))
        self._build_hook_optimizer()

    # -- hooks (the public protocol; ssgwarp.reconstruction.attach makes them during the run) ------------
    @property
    def attached(self) -> bool:
        """Whether the ``attach`` object's hooks have been added (:meth:`add_hooks` with ``attached=True``)."""
        return self._attached

    def add_hooks(self, hooks: Sequence, *, identity_dim: Optional[int] = None, identity_lr: Optional[float] = None,
                  attached: bool = False) -> None:
        """Add ``hooks`` (the protocol of the class docs) to a running trainer: their parameters get an
        optimiser; with ``identity_dim``, a scene without identity encodings gets them (random,
        ``recipe.identity_init_std``, seeded by the run's seed), learnt at ``identity_lr`` (scaled for the
        batch size) or the recipe's. ``attached``: they are the ``attach`` object's (their state goes into
        checkpoints)."""
        self.hooks.extend(hooks)
        if attached:
            self._attached = True
        if identity_dim and "identities" not in self.params:
            g = torch.Generator().manual_seed(self.seed + 2)
            ids = torch.randn(self.num_gaussians, int(identity_dim), generator=g) * self.recipe.identity_init_std
            p = torch.nn.Parameter(ids.to(self.device, torch.float32))
            self.params["identities"] = p
            lr = self.learning_rate("identities") if identity_lr is None else self.lr_factor * float(identity_lr)
            self.opt.add_param_group({"params": [p], "lr": lr, "name": "identities"})
        self._build_hook_optimizer()

    def _build_hook_optimizer(self) -> None:
        hook_groups = [g for h in self.hooks for g in h.parameters()]
        self.hook_opt = adam(hook_groups, betas=self.betas) if hook_groups else None
        if self.hook_opt is not None and self.lr_factor != 1.0:
            for g in self.hook_opt.param_groups:
                g["lr"] *= self.lr_factor
        self._hook_takes_scene = [takes_scene(h) for h in self.hooks]

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
        return sh_degree_at(self.step, self.sh_degree, self.recipe)

    @property
    def scene(self) -> GaussianScene:
        """The current scene (tensors are the live parameters)."""
        p = self.params
        return GaussianScene(p["means"], p["log_scales"], p["quats"], p["logit_opacities"], p["sh_dc"],
                             p.get("sh_rest"), p.get("identities"), self.sh_degree)

    def final_scene(self) -> GaussianScene:
        """A detached copy of the scene (after the last step's loss check)."""
        self._settle_loss()
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
        lr0, lr1 = r.lr_means * self.extent, r.lr_means_final * self.extent
        self.gaussians.groups["means"]["lr"] = self.lr_factor * self.schedules.means_lr(self.step, lr0, lr1)

    def train_step(self) -> dict:
        """One optimisation step (``self.step`` counts completed steps)."""
        r = self.recipe
        attach = self.attach
        if attach is not None and not self._attached and self.step >= attach.start_at(self.schedules.end):
            attach_hooks(self)
        views = self.group.share(self.next_batch())  # this process's views of the step's batch
        self._set_lrs()
        scene = self.scene
        with_ids = bool(self.hooks) and scene.identities is not None
        # (one view: no copy of its image, its cameras made once per resolution level; coarse-to-fine: downsampled)
        level = self.schedules.views(self.step)
        cam, gt, bg = self._views(views, 3 + (scene.identities.shape[1] if with_ids else 0), level,
                                  self.schedules.factor(self.step))
        masks = None if level[2] is None else level[2][views]
        app = self._appearance_step()
        own_bg = app is not None or self.environment is not None  # composited here, not by the rasterizer
        out, alphas, meta = render(scene, cam, sh_degree=self.active_sh_degree, identities=with_ids,
                                   backgrounds=torch.zeros_like(bg) if own_bg else bg, rasterize=self.rasterize,
                                   from_parameters=True, **self.raster_kwargs)
        means2d = meta["means2d"]
        if self.strategy.uses_means2d_grad and means2d.requires_grad:
            means2d.retain_grad()
        img = out if out.shape[-1] == 3 else out[..., :3]  # (a slice's backward would copy the whole gradient)
        if own_bg:  # the sky behind the splats, each photo's exposure and white balance (ImageModel)
            img = self._picture(app, views, img, alphas, cam, gt, bg, masks)
        if masks is not None:  # masked pixels are zero in both: no error, no gradient, no SSIM content
            img, gt = masked(img, gt, masks)
        loss = photometric(img, gt, r.lambda_dssim, r.dssim_scale)  # (the mean over the views)
        reg = self.strategy.regularizer(self.gaussians)
        if reg is not None:
            loss = loss + reg
        hook_losses = []
        if with_ids:
            for h, wants_scene in zip(self.hooks, self._hook_takes_scene):
                extra = {"scene": self.scene} if wants_scene else {}
                per_view = [h.loss(self.step, vi, out[j, ..., 3:], **extra) for j, vi in enumerate(views)]
                hook_losses.append(sum(per_view) / len(per_view))
        total = loss + sum(hook_losses) if hook_losses else loss
        finite_t = torch.isfinite(total.detach())
        self._settle_loss()  # the previous step's flag (long computed: no wait)
        deferred = self._watch_loss(finite_t)
        total.backward()
        zero_unrendered_grads(self.params, with_ids)
        if deferred:
            finite = True  # (known on the host next step: see _watch_loss)
        else:
            # read once the backward is queued: the GPU works through the forward while the host
            # queues the backward. A NaN/inf loss still stops before the optimiser step.
            finite = bool(finite_t)
            if not finite and not self.group.active:
                self._diverged("the loss is NaN/inf")
        # every process steps with the batch's mean gradient; NaN and Ctrl-C anywhere are seen everywhere
        bad, stop = self.group.average_grads(list(self.params.values()) + self._hook_params() + self._env_params(),
                                             [0.0 if finite else 1.0, 1.0 if self._stop_requested else 0.0])
        self._agreed_stop = stop > 0
        if bad > 0:
            self._diverged("the loss is NaN/inf" + ("" if not self.group.active else
                                                    f" on {int(bad)} of {self.group.world_size} processes"))
        observe_across(self.strategy, self.gaussians, meta, self.group)   # (several processes: all their views)
        for o in self._optimisers():
            adam_step(o)  # (step, gradients set to None; the fused update without Adam.step's Python)
        self.step += 1
        info = StepInfo(total.detach(), img.detach(), gt)
        info.update(self.strategy.step(self.gaussians, self.step, self.gaussians.groups["means"]["lr"]))
        if self.pruning is not None:
            info.update(self.pruning.step(self.gaussians, self.step, lambda: self.data.cameras[self.data.train_ids]))
        if self.check_every and self.step % self.check_every == 0:
            self.group.check_identical(self._synced_tensors(), self.step)
        # (--iters auto: every process decides on rank 0's PSNR; theirs differ by float roundoff)
        self.schedules.check(self.step, lambda ids: self.group.broadcast(self.evaluate(ids)["psnr"]), self._loop)
        return info

    def _synced_tensors(self) -> dict[str, torch.Tensor]:
        """What every process must hold identically: parameters, Adam moments, statistics."""
        out = {f"param.{k}": v for k, v in self.params.items()}
        for k, p in self.params.items():
            out.update({f"adam.{k}.{n}": v for n, v in self.gaussians._moments(p).items()})
        out.update({f"stat.{k}": v for k, v in self.gaussians.stats.items()})
        out.update({f"hook.{i}": p for i, p in enumerate(self._hook_params())})
        return out

    @property
    def _stop_requested(self) -> bool:
        return self._loop is not None and self._loop.stop_requested

    def _optimisers(self) -> list:
        return [o for o in (self.opt, self.hook_opt, self.env_opt) if o is not None]

    def _watch_loss(self, finite: torch.Tensor) -> bool:
        """:meth:`LossWatch.watch` of this step's loss flag (False: the caller reads it now)."""
        return self._losses.watch(finite, self._optimisers(), self.step + 1, self.group.active)

    def _settle_loss(self) -> None:
        """Raise :class:`Diverged` if the step whose loss flag is pending had a NaN/inf loss (its
        updates were skipped; the last good checkpoint is kept)."""
        bad = self._losses.settle()
        if bad is not None:
            self._diverged("the loss is NaN/inf", bad)

    def _diverged(self, why: str, step: Optional[int] = None) -> None:
        where = (f"the last good checkpoint (step {self.last_checkpoint_step}) is kept at {self.checkpoint_path}"
                 if self.last_checkpoint_step is not None else "no checkpoint was written yet")
        raise Diverged(diverged_message(self.step + 1 if step is None else step, where, why))

    def train(self, until: Optional[int] = None) -> GaussianScene:
        """Train up to step ``until`` (default: the run's end, ``iters`` or where ``--iters auto`` stops)
        under :mod:`ssgwarp.services.loop`'s policy: checkpoints every ``checkpoint_every`` steps, at the end
        and on Ctrl-C (the step in flight finishes first); a NaN loss stops with the last good checkpoint kept."""
        cap = self.iters if until is None else min(int(until), self.iters)
        until = lambda: min(cap, self.schedules.end)  # noqa: E731  (--iters auto: the stop rule may end it sooner)
        save = self.save_checkpoint if self.checkpoint_path is not None else None
        active = self.group.active
        loop = Loop(lambda: self.step, save=save, every=self.checkpoint_every, desc="reconstruct",
                    progress=self.progress, total=until(), sigterm=active, second_raises=not active,
                    stop_agreed=(lambda: self._agreed_stop) if active else None,
                    after_stop=self.group.barrier, say=self.group.is_main)   # nobody leaves before the checkpoint is written
        loop.saved_step = self.last_checkpoint_step
        t0 = time.time() - self.elapsed
        ema = [None]

        def on_step(info: dict) -> None:
            self.elapsed = time.time() - t0
            if self.step % 10 == 0 or self.step == until():
                p = -10.0 * math.log10(max(float(info["mse"]), 1e-10))
                ema[0] = p if ema[0] is None else 0.9 * ema[0] + 0.1 * p
                loop.bar.set_postfix(loss=f"{float(info['loss']):.4f}", psnr=f"{ema[0]:.2f}",
                                     gaussians=self.num_gaussians, sh=self.active_sh_degree, refresh=False)
                self.history.append({"step": self.step, "loss": float(info["loss"]), "psnr": p,
                                     "gaussians": self.num_gaussians})

        self._loop = loop
        try:
            loop.run(self.train_step, until, on_step)
        finally:
            self._loop = None
            self._agreed_stop = False
        return self.final_scene()

    # -- checkpoints (the state and its file: ssgwarp.reconstruction.checkpoint.TrainState) --------------
    def state_dict(self) -> dict:
        """The checkpoint's contents (:meth:`TrainState.of`)."""
        return TrainState.of(self).state

    def load_state_dict(self, st: dict) -> None:
        """Continue from a checkpoint's contents (:meth:`TrainState.restore`)."""
        TrainState(st).restore(self)

    def save_checkpoint(self, path: Optional[str | Path] = None) -> Path:
        """Write the checkpoint (with several processes: the main one writes, the others only note the step).
        A step whose loss was NaN/inf is never written: its flag is read first (:meth:`_settle_loss`)."""
        self._settle_loss()
        path = Path(path) if path is not None else self.checkpoint_path
        if path is None:
            raise ValueError("no checkpoint path")
        if self.group.is_main:
            TrainState.of(self).save(path)
        self.last_checkpoint_step = self.step
        return path

    def load_checkpoint(self, path: Optional[str | Path] = None, state: Optional[dict] = None) -> None:
        """Continue from the checkpoint at ``path`` (default: this run's), or from its already
        read ``state`` (:meth:`TrainState.read`)."""
        path = Path(path) if path is not None else self.checkpoint_path
        (TrainState(state) if state is not None else TrainState.read(path)).restore(self, where=path)
        log.info("resumed from %s at step %d", path, self.step)

