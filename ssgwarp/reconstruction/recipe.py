"""The 3DGS training recipe: :class:`Recipe` (learning rates, loss weights, densification knobs,
resolved for a run's length, strategy and batch size) and :func:`batch_factors` (Adam for batches).
The loop that follows it is :class:`ssgwarp.reconstruction.trainer.Trainer`."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from ..errors import InputError
from .strategy import REFINE_EPOCHS, make_strategy

BATCH_SCALINGS = ("sqrt", "linear", "none")
_STEP_FIELDS = ("sh_interval", "refine_start", "refine_stop", "refine_every", "reset_every")




@dataclass
class Recipe:
    """Training knobs; defaults are the 3DGS paper's (3DGS-MCMC's where the strategy says so).

    Step counts are absolute. Fields left None are resolved for the run by :meth:`resolved`:
    ``sh_interval`` is ``min(1000, iters // (2 * sh_degree))`` so short runs still reach their
    degree; the refine schedule (``refine_start``, ``refine_stop``, ``refine_every``,
    ``reset_every``) is the strategy's reference schedule at 30,000 steps scaled to ``iters``
    (:func:`ssgwarp.reconstruction.strategy.scaled_schedule`); ``init_opacity``, ``init_scale``,
    ``opacity_reg`` and ``scale_reg`` are the strategy's (default: 0.1, 1, 0, 0, the scale
    thinned for a dense cloud of random points by :func:`ssgwarp.reconstruction.strategy.random_init_scale`;
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
    # -- densification (ssgwarp.reconstruction.strategy) --
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
    far_split_px: float = 8.0          # far Gaussians wider than this on screen (pixels) get their gradient
                                       # statistic scaled by their width / this (far_field.py); 0: off
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
    # -- schedules (ssgwarp.reconstruction.schedules) --
    sh_start: Optional[int] = None     # step of the first SH degree raise, then one every sh_interval
                                       # (default: sh_interval)
    res_start: float = 1.0             # coarse-to-fine: the training images downsampled by this factor at
                                       # first (1: off; 4: 4, 2.83, 2, 1.41, then full resolution)
    res_until: Optional[int] = None    # full resolution from this step on (default: refine_stop)
    stop_every: Optional[int] = None   # --iters auto: steps between checks (default: 500 images)
    stop_patience: int = 3             # --iters auto: checks without stop_tol dB of improvement that stop
    stop_tol: float = 0.1              # --iters auto: dB of training-view PSNR
    stop_views: int = 4                # --iters auto: training views checked (evenly spaced)
    stop_tail: float = 0.2             # --iters auto: steps trained after the plateau, a fraction of the steps
                                       # done (the position learning rate decays to its final value over them)

    def resolved(self, iters: int, sh_degree: int, strategy="default", random_init: Optional[int] = None,
                 batch_size: int = 1, views: Optional[int] = None) -> "Recipe":
        """The recipe with every None field set for a run of ``iters`` steps of ``batch_size`` views
        with ``strategy`` (``random_init``: the number of initial points when they are random, not
        a point cloud).

        Defaults are set for the run's number of images (``iters * batch_size``) and then counted
        in steps (divided by ``batch_size``): a batch run refines, resets opacities and raises the
        SH degree after the same number of images as a one-view run. Values given are steps.

        ``views``: the number of training views. Densification stops, by default, once every view was seen
        :data:`~ssgwarp.reconstruction.strategy.REFINE_EPOCHS` times (when that comes before the scaled
        ``refine_stop``): a sparse capture trained long would otherwise keep densifying on the same few images
        (fern's 17 views at 30,000 steps: 880 passes each, 762k Gaussians)."""
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
        if views and fill.get("refine_stop") and fill["refine_stop"] > REFINE_EPOCHS * int(views):
            start = fill.get("refine_start", r.refine_start) or 0
            every = fill.get("refine_every", r.refine_every) or 1
            fill["refine_stop"] = max(REFINE_EPOCHS * int(views), start + every + 1)
        for k in _STEP_FIELDS:  # images -> steps
            if fill.get(k):
                fill[k] = max(1, round(fill[k] / b))
        r = replace(r, **fill)
        if r.reset_every is None:
            r = replace(r, reset_every=0)
        late = {"sh_start": r.sh_interval, "res_until": r.refine_stop, "stop_every": max(1, round(500 / b))}
        r = replace(r, **{k: v for k, v in late.items() if getattr(r, k) is None})
        if r.res_start < 1.0 or r.stop_patience < 1 or r.stop_views < 1 or r.stop_tail < 0:
            raise InputError("Recipe.res_start must be >= 1, stop_patience and stop_views >= 1, stop_tail >= 0")
        for k in ("refine_every", "sh_interval"):
            if getattr(r, k) < 1:
                raise InputError(f"Recipe.{k} must be >= 1, got {getattr(r, k)}")
        if r.reset_every < 0 or r.refine_start < 0:
            raise InputError("Recipe.reset_every and Recipe.refine_start must be >= 0")
        return r
