"""The 3DGS training recipe: :class:`Recipe` (what every strategy shares: learning rates, loss weights, the SH,
resolution and stop schedules, initialisation, Adam for batches), and :func:`resolve` / :func:`resolve_run`, which
turn a recipe, a densification strategy (:mod:`ssgwarp.reconstruction.strategy`: its own knobs, as a dataclass)
and a run (its length, ``--iters auto``, the capture, the batch size) into concrete values. The loop that
follows them is :class:`ssgwarp.reconstruction.trainer.Trainer`.

:func:`options_record` is the recipe's and strategy's part of a run's resume record; :func:`upgrade_record`
reads one written before the strategies had their own dataclass (one flat ``recipe``)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Optional

import numpy as np

from ..errors import InputError
from .schedules import AUTO, AUTO_MAX_ITERS
from .strategy import REFINE_EPOCHS, Strategy, make_strategy

BATCH_SCALINGS = ("sqrt", "linear", "none")
OPTIMIZERS = ("torch", "warp")
_STEP_FIELDS = ("sh_interval", "refine_start", "refine_stop", "refine_every", "reset_every")


@dataclass
class Recipe:
    """Training knobs every strategy shares; defaults are the 3DGS paper's. The densification knobs (refine
    schedule, thresholds, budget) are the strategy's (:class:`~ssgwarp.reconstruction.strategy.DefaultStrategy`,
    :class:`~ssgwarp.reconstruction.strategy.MCMCStrategy`).

    Step counts are absolute. Fields left None are resolved for the run by :func:`resolve`:
    ``sh_interval`` is ``min(1000, iters // (2 * sh_degree))`` so short runs still reach their
    degree; ``init_opacity`` and ``init_scale`` are the strategy's (default: 0.1, 1, the scale
    thinned for a dense cloud of random points by :func:`ssgwarp.reconstruction.strategy.random_init_scale`;
    mcmc: 0.5, 0.1).
    """

    sh_degree: int = 3                 # final SH degree (0..3)

    lr_means: float = 1.6e-4           # times the scene extent
    lr_means_final: float = 1.6e-6     # times the scene extent, reached at the last step
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_identities: float = 2.5e-3
    adam_eps: float = 1e-15
    optimizer: str = "torch"           # the scene's Adam: "torch" (torch's fused Adam, one launch per tensor) or
                                       # "warp" (ssgwarp.raster.adam_ops.WarpAdam: one launch for all of them)
    lambda_dssim: float = 0.2
    dssim_scale: float = 1.0           # multiplies the D-SSIM term; 0.5: the halved (1 - SSIM) / 2 of old runs
    sh_interval: Optional[int] = None
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
    res_until: Optional[int] = None    # full resolution from this step on (default: the strategy's refine_stop)
    stop_every: Optional[int] = None   # --iters auto: steps between checks (default: 500 images)
    stop_patience: int = 3             # --iters auto: checks without stop_tol dB of improvement that stop
    stop_tol: float = 0.1              # --iters auto: dB of training-view PSNR
    stop_views: int = 4                # --iters auto: training views checked (evenly spaced)
    stop_tail: float = 0.2             # --iters auto: steps trained after the plateau, a fraction of the steps
                                       # done (the position learning rate decays to its final value over them)


def resolve(recipe: Recipe, strategy: Any = "default", iters: int = 30_000, *, random_init: Optional[int] = None,
            batch_size: int = 1, views: Optional[int] = None) -> tuple[Recipe, Strategy]:
    """``(recipe, strategy)`` with every None field set for a run of ``iters`` steps of ``batch_size`` views
    (``strategy``: a :class:`~ssgwarp.reconstruction.strategy.Strategy` or its name; a new one is returned,
    the given one is left as it is; ``random_init``: the number of initial points when they are random, not a
    point cloud).

    Defaults are set for the run's number of images (``iters * batch_size``) and then counted in steps
    (divided by ``batch_size``): a batch run refines, resets opacities and raises the SH degree after the same
    number of images as a one-view run. Values given are steps.

    ``views``: the number of training views. Densification stops, by default, once every view was seen
    :data:`~ssgwarp.reconstruction.strategy.REFINE_EPOCHS` times (when that comes before the scaled
    ``refine_stop``): a sparse capture trained long would otherwise keep densifying on the same few images
    (fern's 17 views at 30,000 steps: 880 passes each, 762k Gaussians)."""
    r, s = recipe, make_strategy(strategy)
    if r.batch_scaling not in BATCH_SCALINGS:
        raise InputError(f"Recipe.batch_scaling {r.batch_scaling!r}: choose one of {', '.join(BATCH_SCALINGS)}")
    if r.optimizer not in OPTIMIZERS:
        raise InputError(f"Recipe.optimizer {r.optimizer!r}: choose one of {', '.join(OPTIMIZERS)}")
    if not 0 <= r.sh_degree <= 3:
        raise InputError(f"sh_degree must be 0..3, got {r.sh_degree}")
    if s.max_gaussians < 1:
        raise InputError(f"max_gaussians must be >= 1, got {s.max_gaussians}")
    b = max(1, int(batch_size))
    images = iters * b
    fill = {}
    if r.sh_interval is None:
        fill["sh_interval"] = max(1, min(1000, images // (2 * max(1, r.sh_degree))))
    knobs = set(s.knobs())
    for k, v in s.defaults(images, random_init).items():   # (a value neither has, e.g. mcmc's reset_every: none)
        if getattr(s if k in knobs else r, k, 0) is None:
            fill[k] = v
    if views and fill.get("refine_stop") and fill["refine_stop"] > REFINE_EPOCHS * int(views):
        start = fill.get("refine_start", s.refine_start) or 0
        every = fill.get("refine_every", s.refine_every) or 1
        fill["refine_stop"] = max(REFINE_EPOCHS * int(views), start + every + 1)
    for k in _STEP_FIELDS:  # images -> steps
        if fill.get(k):
            fill[k] = max(1, round(fill[k] / b))
    s = replace(s, **{k: v for k, v in fill.items() if k in knobs})
    r = replace(r, **{k: v for k, v in fill.items() if k not in knobs})
    if "reset_every" in knobs and s.reset_every is None:
        s = replace(s, reset_every=0)
    late = {"sh_start": r.sh_interval, "res_until": s.refine_stop, "stop_every": max(1, round(500 / b))}
    r = replace(r, **{k: v for k, v in late.items() if getattr(r, k) is None})
    if r.res_start < 1.0 or r.stop_patience < 1 or r.stop_views < 1 or r.stop_tail < 0:
        raise InputError("Recipe.res_start must be >= 1, stop_patience and stop_views >= 1, stop_tail >= 0")
    if r.sh_interval < 1:
        raise InputError(f"Recipe.sh_interval must be >= 1, got {r.sh_interval}")
    if s.refine_every < 1:
        raise InputError(f"{type(s).__name__}.refine_every must be >= 1, got {s.refine_every}")
    if getattr(s, "reset_every", 0) < 0 or s.refine_start < 0:
        raise InputError(f"{type(s).__name__}.reset_every and .refine_start must be >= 0")
    return r, s


def initial_count(n: int, recipe: Recipe, strategy: Strategy) -> int:
    """How many of ``n`` capture points start the scene (``init_max_points``; the budget of a budgeted strategy)."""
    if recipe.init_max_points is not None:
        n = min(n, recipe.init_max_points)
    return min(n, strategy.max_gaussians) if strategy.budgeted else n


@dataclass(frozen=True)
class RunPlan:
    """What :func:`resolve_run` decided for a run: its length (``auto``: ``--iters auto``, planned as
    :data:`~ssgwarp.reconstruction.schedules.AUTO_MAX_ITERS` steps), the resolved recipe and strategy."""

    iters: int
    auto: bool
    recipe: Recipe
    strategy: Strategy


def resolve_run(data, recipe: Optional[Recipe] = None, strategy: Any = "default", iters: int | str = 30_000, *,
                scene_given: bool = False, batch_size: int = 1) -> RunPlan:
    """The :class:`RunPlan` of a reconstruction of capture ``data`` (its training views and, unless
    ``scene_given``, its initial points: random ones thin the initial scale) with ``recipe`` (default:
    :class:`Recipe`'s), ``strategy`` and ``iters`` (steps or ``"auto"``), ``batch_size`` views per step."""
    auto = iters == AUTO
    iters = AUTO_MAX_ITERS if auto else iters
    if not isinstance(iters, (int, np.integer)) or iters < 1:
        raise InputError(f"iters must be >= 1 or {AUTO!r}, got {iters!r}")
    recipe = recipe or Recipe()
    s = make_strategy(strategy)
    random_init = None
    if not scene_given and getattr(data, "points_source", "") == "random" and data.points is not None:
        random_init = initial_count(len(data.points[0]), recipe, s)
    r, s = resolve(recipe, s, int(iters), random_init=random_init, batch_size=batch_size,
                   views=len(data.train_ids))
    return RunPlan(int(iters), auto, r, s)


# ----------------------------------------------------------------------------- the resume record
# the flat ``recipe`` of a resume record written before the strategies had their own dataclass: each strategy's
# knobs under their old names (the rest of that flat dict is the Recipe's, under the same names)
FLAT_KNOBS = {
    "default": {"refine_start": "refine_start", "refine_stop": "refine_stop", "refine_every": "refine_every",
                "reset_every": "reset_every", "grad_threshold": "grad_threshold", "percent_dense": "percent_dense",
                "split_factor": "split_factor", "prune_opacity": "prune_opacity", "reset_opacity": "reset_opacity",
                "prune_world": "prune_world", "prune_screen": "prune_screen"},
    "mcmc": {"refine_start": "refine_start", "refine_stop": "refine_stop", "refine_every": "refine_every",
             "prune_opacity": "prune_opacity", "mcmc_growth": "growth", "noise_lr": "noise_lr",
             "opacity_reg": "opacity_reg", "scale_reg": "scale_reg"},
}
_FLAT_ONLY = set().union(*FLAT_KNOBS.values())   # every key of the old flat recipe that is no Recipe field now

def options_record(recipe: Optional[Recipe], strategy: Any) -> dict:
    """The recipe's and the strategy's part of a reconstruction's resume record (the options a resume must
    repeat): their command-line options by name (``--sh-degree``, ``--strategy``, ``--max-gaussians``,
    ``--coarse-to-fine``, ``--batch-scaling``), the other recipe fields as ``recipe``, the strategy's other
    knobs as ``strategy`` (a change reads ``strategy.grad_threshold 0.0002 -> 0.0003``)."""
    r = asdict(recipe if recipe is not None else Recipe())
    s = make_strategy(strategy)
    knobs = asdict(s)
    return {"--sh-degree": r.pop("sh_degree"), "--strategy": s.name, "--max-gaussians": knobs.pop("max_gaussians"),
            "--coarse-to-fine": r.pop("res_start", None), "--batch-scaling": r.pop("batch_scaling", None),
            "recipe": r, "strategy": knobs}


def upgrade_record(old: Optional[dict]) -> Optional[dict]:
    """A resume record as :func:`options_record` writes it today, from one written before (one flat ``recipe``
    holding every strategy's knobs; ``--sh-degree``, ``--strategy`` and ``--max-gaussians`` as today). The
    knobs of the record's strategy move to ``strategy`` (renamed where their name changed; a None, which the
    run resolved to the strategy's default, becomes the field's default where that is a value), the other
    strategy's knobs (which had no effect) are dropped. A field added since the record was written (absent from
    it) reads as its default, which is what the earlier version ran with. None is returned as is."""
    if not isinstance(old, dict) or not isinstance(old.get("recipe"), dict):
        return old
    name = old.get("--strategy", "default")
    if name not in FLAT_KNOBS:
        return old
    fresh = options_record(None, name)   # (the defaults' record: every field of today, in today's layout)
    recipe, knobs = {**fresh["recipe"], **old["recipe"]}, fresh["strategy"]
    if isinstance(old.get("strategy"), dict):
        return {**old, "recipe": recipe, "strategy": {**knobs, **old["strategy"]}}
    for k_old, k_new in FLAT_KNOBS[name].items():
        if recipe.get(k_old) is not None:
            knobs[k_new] = recipe[k_old]
    for k in _FLAT_ONLY:
        recipe.pop(k, None)
    return {**old, "recipe": recipe, "strategy": knobs}
