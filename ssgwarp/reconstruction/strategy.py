"""Densification strategies: how the set of Gaussians changes while a scene trains.

A :class:`~ssgwarp.reconstruction.reconstruct.Trainer` owns the Gaussians' tensors and their Adam
optimizer in a :class:`~ssgwarp.reconstruction.gaussians.GaussianParams`; a :class:`Strategy` decides when rows are
added, removed or rewritten, and does it through that object's row surgery
(:meth:`GaussianParams.keep`, :meth:`~GaussianParams.append`,
:meth:`~GaussianParams.assign`), which keeps every per-Gaussian tensor (means,
scales, rotations, opacities, SH bands, identity encodings, the strategy's own
statistics) and the Adam moments of each in step.

The interface the Trainer calls, once per training step::

    loss = photometric + strategy.regularizer(gaussians)      # (None: no term)
    loss.backward()
    strategy.observe(gaussians, meta)                         # statistics of this render
    optimizer.step()
    info = strategy.step(gaussians, step, lr_means)           # refine / reset / perturb

With several processes (:mod:`ssgwarp.services.distributed`) each observes its own views into zeroed
statistics, which are then combined across processes by :attr:`Strategy.stat_ops` and added to
the running ones, so every process refines identically.

Plus :meth:`Strategy.setup` (before the first step), :meth:`Strategy.defaults`
(the values it resolves: its schedule, the recipe's initialisation) and the state of its random
generator for checkpoints.

Each strategy is a dataclass of its knobs (as gsplat's strategies): ``max_gaussians`` and the refine
schedule for all, thresholds, opacity reset, relocation and regularisers per strategy; the knobs every
strategy shares (learning rates, loss weights, the SH schedule...) are the
:class:`~ssgwarp.reconstruction.recipe.Recipe`'s. :func:`ssgwarp.reconstruction.recipe.resolve` sets the
fields left None for a run.

Strategies:

* :class:`DefaultStrategy` (``--strategy default``): the 3DGS rules (Kerbl et al.
  2023): clone / split by the mean view-space positional gradient in NDC units,
  prune by opacity and size, periodic opacity reset.
* :class:`MCMCStrategy` (``--strategy mcmc``): 3DGS as Markov chain Monte Carlo
  (Kheradmand et al. 2024): dead Gaussians are relocated onto live ones sampled by
  opacity, new ones are added the same way up to a fixed budget, positions get
  opacity-gated noise, and L1 regularisers on opacity and scale.

The refine schedule scales with the run's length (:func:`scaled_schedule`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar, Optional

import torch

from ..errors import InputError
from ..core.geometry import quat_to_rotmat
from .far_field import FarField
from .gaussians import GaussianParams
from .statistics import accumulate_grad2d

# ----------------------------------------------------------------------------- schedule
REFERENCE_ITERS = 30_000      # the run length the 3DGS / 3DGS-MCMC schedules were set for
MIN_REFINE_EVERY = 100        # steps between refinements, at least: new Gaussians need about that long to settle
MIN_RESET_EVERY = 300         # an opacity reset needs a few hundred steps to recover (logits move ~lr per step)
REFINE_EPOCHS = 200           # default densification ends once every training view was seen this many times
                              # (fern 7k: 3,500 steps for 17 views, 206 passes: 27.3 dB)
RANDOM_INIT_POINTS = 2000     # random initial clouds denser than this start with narrower Gaussians (random_init_scale)


def random_init_scale(n_points: int) -> float:
    """Initial scale (times the 3-nearest-neighbour distance) of ``n_points`` random points.

    Random points fill the cameras' view, and Gaussians as wide as their neighbour distance
    make a fog whose optical depth along a ray grows as ``N^(1/3)`` (density ``N / V`` times
    cross-section ``(V / N)^(2/3)`` times depth ``V^(1/3)``); a thick fog takes a short run all
    its steps to clear. Scaling the widths by ``(2000 / N)^(1/6)`` keeps the fog of any denser
    cloud at that of 2,000 points. Measured (held-out PSNR): lego, 100k random points, 500
    steps: 15.36 dB at scale 1, 25.41 dB at 0.46, 25.48 dB at 0.3 (the rule: 0.52); the demo
    scenes keep scale 1: 600 points, 150 steps, 18.8 dB (15.4 dB at 0.46); 2,000 points,
    1,000 steps, 33.76 dB (32.69 dB at 0.89).
    """
    return min(1.0, (RANDOM_INIT_POINTS / max(1, int(n_points))) ** (1.0 / 6.0))


@dataclass(frozen=True)
class Schedule:
    """When a strategy refines (completed-step counts): every ``refine_every`` steps in
    ``[refine_start, refine_stop)``; opacity reset every ``reset_every`` steps before
    ``refine_stop`` (0: never)."""

    refine_start: int
    refine_stop: int
    refine_every: int
    reset_every: int = 0

    def refines_at(self, step: int) -> bool:
        return self.refine_start <= step < self.refine_stop and step % self.refine_every == 0

    def resets_at(self, step: int) -> bool:
        return self.reset_every > 0 and 0 < step < self.refine_stop and step % self.reset_every == 0

    def after_first_reset(self, step: int) -> bool:
        return self.reset_every > 0 and step > self.reset_every


def scaled_schedule(iters: int, *, refine_start: int, refine_stop: int, refine_every: int,
                    reset_every: int = 0) -> dict:
    """The reference schedule (step counts at :data:`REFERENCE_ITERS`) scaled to a run of ``iters`` steps.

    Every step count is multiplied by ``iters / 30000``, with two floors so that short runs stay
    sensible: refinements at least :data:`MIN_REFINE_EVERY` steps apart, the first not before one
    interval (clones and split children start with fresh Adam moments and need about a hundred
    steps to settle; measured on lego at 100 px, 500 steps: refining every 10 steps from step 10
    lost 7.7 dB against no densification, every 87 from 87 gained 0.4 dB); opacity resets at least
    :data:`MIN_RESET_EVERY` steps apart (a short run whose reset interval reaches ``refine_stop``
    has no reset, and no size pruning, which starts after the first reset). Longer runs stretch
    every interval; at 30,000 steps this is the reference itself.
    """
    f = iters / REFERENCE_ITERS
    every = max(MIN_REFINE_EVERY, round(refine_every * f))
    out = {"refine_every": every, "refine_start": max(every, round(refine_start * f)),
           "refine_stop": max(1, round(refine_stop * f)), "reset_every": 0}
    if reset_every:
        out["reset_every"] = max(MIN_RESET_EVERY, round(reset_every * f))
    return out


# ----------------------------------------------------------------------------- strategies
@dataclass
class Strategy:
    """Base class: no densification (the set of Gaussians stays as it is).

    A strategy is a dataclass of its knobs (as gsplat's strategies): the ones here are every strategy's,
    subclasses add their own. Schedule fields left None are resolved for the run
    (:func:`ssgwarp.reconstruction.recipe.resolve`: the strategy's :attr:`reference` schedule at 30,000 steps
    scaled to the run, :func:`scaled_schedule`); the run's state (the bound Gaussians' extent, the schedule,
    the random generator) is set by :meth:`setup` and is not a field."""

    max_gaussians: int = 1_000_000          # cap on the number of Gaussians (mcmc: the budget it grows to)
    refine_start: Optional[int] = None      # first refinement (30k reference: 500)
    refine_stop: Optional[int] = None       # no refinement from this step on (default 15000, mcmc 25000 at 30k)
    refine_every: Optional[int] = None      # steps between refinements (30k reference: 100; at least 10)

    name: ClassVar[str] = "none"
    uses_means2d_grad: ClassVar[bool] = False   # the Trainer keeps meta["means2d"].grad for observe()
    budgeted: ClassVar[bool] = False            # max_gaussians is a budget the initial scene must fit in
    stat_ops: ClassVar[dict] = {}   # how each statistic combines over views rendered by several processes:
                                    # "sum" (default) or "max" (ssgwarp.services.distributed.Group.reduce_stats)
    reference: ClassVar[dict] = {"refine_start": REFERENCE_ITERS, "refine_stop": 0, "refine_every": REFERENCE_ITERS}
    recipe_defaults: ClassVar[dict] = {"init_opacity": 0.1, "init_scale": 1.0}   # Recipe fields it resolves

    def __post_init__(self):
        self.recipe = None
        self.extent = 1.0
        self.schedule = Schedule(0, 0, 1)
        self.generator: Optional[torch.Generator] = None
        self.center: Optional[torch.Tensor] = None   # far field (far_field): sizes beyond scene_radius of
        self.scene_radius: Optional[float] = None    # center are measured against the distance from it
        self.far: Optional[FarField] = None          # far-field densification statistic (far_field.py)

    @classmethod
    def knobs(cls) -> tuple[str, ...]:
        """The names of this strategy's fields."""
        return tuple(f.name for f in fields(cls))

    def far_field(self, center: torch.Tensor, scene_radius: float, focal_px: Optional[float] = None) -> None:
        """Measure the size rules of Gaussians farther than ``scene_radius`` from ``center`` (the cameras'
        centroid) against ``extent x distance / scene_radius`` instead of the extent (a backdrop's far
        Gaussians are large in world units and small on screen); with ``focal_px`` (the training images'
        focal length in pixels) the gradient statistic of far Gaussians is scaled by their footprint
        (:class:`~ssgwarp.reconstruction.far_field.FarField`)."""
        self.center, self.scene_radius = center, float(scene_radius)
        split_px = getattr(self, "far_split_px", 0.0)
        self.far = FarField.around(center, self.extent, focal_px, split_px) if focal_px and split_px > 0 else None

    def size_reference(self, means: torch.Tensor) -> torch.Tensor | float:
        """``[N]`` (or a number) the length sizes are compared to: the extent, times ``distance / scene_radius``
        beyond the scene radius when a far field is set."""
        if self.center is None or not self.scene_radius:
            return self.extent
        d = (means - self.center.to(means.device, means.dtype)).norm(dim=1)
        return self.extent * (d / self.scene_radius).clamp_min(1.0)

    def defaults(self, iters: int, random_init: Optional[int] = None) -> dict:
        """Values this strategy resolves when they are left None: its schedule scaled to ``iters``
        (:func:`scaled_schedule`; its own fields) and the recipe's initialisation (:attr:`recipe_defaults`).
        ``random_init``: the number of initial points when they are random (no point cloud)."""
        return {**scaled_schedule(iters, **self.reference), **self.recipe_defaults}

    def setup(self, gaussians: GaussianParams, *, recipe, extent: float, seed: int) -> None:
        """Bind to a run (this strategy and ``recipe`` already resolved); register per-Gaussian statistics in
        ``gaussians.stats``."""
        self.recipe = recipe
        self.extent = float(extent)
        self.schedule = Schedule(self.refine_start, self.refine_stop, self.refine_every,
                                 getattr(self, "reset_every", 0) or 0)
        self.generator = self._make_generator(gaussians.device, seed)

    def _make_generator(self, device: torch.device, seed: int) -> torch.Generator:
        return torch.Generator().manual_seed(seed + 1)

    def regularizer(self, gaussians: GaussianParams) -> Optional[torch.Tensor]:
        """An extra loss term on the Gaussians (None: none)."""
        return None

    def observe(self, gaussians: GaussianParams, meta: dict) -> None:
        """Called after backward with the render's ``meta`` (``means2d.grad`` filled when ``uses_means2d_grad``)."""

    def step(self, gaussians: GaussianParams, step: int, lr_means: float) -> dict:
        """Called after the optimizer step; ``step`` counts completed steps. Returns what it did."""
        return {}

    def generator_state(self) -> Optional[torch.Tensor]:
        return None if self.generator is None else self.generator.get_state()

    def set_generator_state(self, state: torch.Tensor) -> None:
        if self.generator is not None and state is not None:
            self.generator.set_state(state)


@dataclass
class DefaultStrategy(Strategy):
    """The 3DGS rules (Kerbl et al. 2023), with these thresholds (defaults: the paper's).

    Statistics (per Gaussian, since the last refinement): ``grad2d``, the sum over the
    views in which it was visible of the norm of its view-space positional gradient in
    NDC units (``means2d.grad`` times ``(W/2, H/2)`` and the number of cameras of the
    batch, as the loss averages over them); ``count``, the number of those views; and,
    when screen-size pruning is on, ``max_radii``, its largest screen radius as a
    fraction of the image's larger side.

    At each refinement: a Gaussian whose mean gradient ``grad2d / count`` is at least
    ``grad_threshold`` is cloned (an exact copy appended) when its largest scale is at
    most ``percent_dense`` times the extent, else split (two children sampled from it
    with scales divided by ``split_factor``, the parent removed); when the growth would
    pass ``max_gaussians`` the candidates with the highest gradients win. Then Gaussians
    with opacity below ``prune_opacity`` are removed, and after the first opacity reset
    also those larger than ``prune_world`` times the extent or (``prune_screen`` > 0)
    whose screen radius exceeded ``prune_screen`` of the image's larger side. Opacity
    reset every ``reset_every`` steps: opacities capped at ``reset_opacity``, their Adam
    moments zeroed.
    """

    reset_every: Optional[int] = None   # opacity reset interval (30k: 3000; at least 300); 0: none
    grad_threshold: float = 2e-4        # mean view-space positional gradient, NDC units (gsplat / INRIA)
    percent_dense: float = 0.01         # clone if max scale <= this x extent, else split
    split_factor: float = 1.6           # children scales = parent / split_factor
    prune_opacity: float = 0.005        # pruned below it
    reset_opacity: float = 0.01         # opacities capped at it by a reset
    prune_world: float = 0.1            # prune when max scale > this x extent (after the first reset)
    prune_screen: float = 0.0           # prune when the screen radius exceeded this fraction of max(W, H)
                                        # (after the first reset); 0: off
    prune_contribution: float = 0.0     # prune Gaussians whose blending weight per training view is below this
                                        # many pixels (ssgwarp.reconstruction.pruning; the trainer runs it); 0: off
    prune_budget: int = 0               # ... and keep at most this many, the largest contributions (0: none)
    far_split_px: float = 0.0           # far Gaussians wider than this on screen (pixels) get their gradient
                                        # statistic scaled by their width / this (far_field.py); 0: off

    name: ClassVar[str] = "default"
    uses_means2d_grad: ClassVar[bool] = True
    stat_ops: ClassVar[dict] = {"grad2d": "sum", "count": "sum", "max_radii": "max"}
    reference: ClassVar[dict] = {"refine_start": 500, "refine_stop": 15_000, "refine_every": 100, "reset_every": 3000}

    def defaults(self, iters: int, random_init: Optional[int] = None) -> dict:
        out = super().defaults(iters, random_init)
        if random_init:  # the 3DGS start, thinned for dense random clouds
            out["init_scale"] = random_init_scale(random_init)
        return out

    def setup(self, gaussians, *, recipe, extent, seed) -> None:
        super().setup(gaussians, recipe=recipe, extent=extent, seed=seed)
        n = len(gaussians)
        gaussians.stats = {"grad2d": torch.zeros(n, device=gaussians.device),
                           "count": torch.zeros(n, device=gaussians.device)}
        if self.prune_screen > 0:
            gaussians.stats["max_radii"] = torch.zeros(n, device=gaussians.device)

    @torch.no_grad()
    def observe(self, gaussians: GaussianParams, meta: dict) -> None:
        accumulate_grad2d(gaussians.stats, meta)

    def step(self, gaussians: GaussianParams, step: int, lr_means: float) -> dict:
        info = {}
        if self.schedule.refines_at(step):
            info["refine"] = self.refine(gaussians, step)
        if self.schedule.resets_at(step):
            self.reset_opacities(gaussians)
            info["reset"] = True
        return info

    @torch.no_grad()
    def refine(self, g: GaussianParams, step: int) -> dict:
        r = self
        n0 = len(g)
        count = g.stats["count"]
        avg = g.stats["grad2d"] / count.clamp_min(1.0)
        if self.far is not None:
            avg = self.far.statistic(avg, g.params["means"].data, g.params["log_scales"].data)
        high = (avg >= r.grad_threshold) & (count > 0)
        size = torch.exp(g.params["log_scales"].data).max(dim=1).values
        small = size <= r.percent_dense * self.size_reference(g.params["means"].data)
        room = max(0, self.max_gaussians - n0)
        if int(high.sum()) > room:  # the cap: the highest gradients win
            idx = torch.nonzero(high)[:, 0]
            top = idx[avg[idx].argsort(descending=True, stable=True)[:room]]
            high = torch.zeros_like(high)
            high[top] = True
        clone, split = high & small, high & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        children = split_children(g.params, split, r.split_factor, self.generator) if n_split else None
        if n_clone:  # survivors keep their rows, clones follow, then split children; split parents go
            g.append({k: v.data[clone] for k, v in g.params.items()})
        if n_split:
            g.append(children)
            keep = torch.ones(len(g), dtype=torch.bool, device=g.device)
            keep[:n0] = ~split
            g.keep(keep)
        # prune
        prune = torch.sigmoid(g.params["logit_opacities"].data) < r.prune_opacity
        if self.schedule.after_first_reset(step):
            prune |= (torch.exp(g.params["log_scales"].data).max(dim=1).values
                      > r.prune_world * self.size_reference(g.params["means"].data))
            if "max_radii" in g.stats:
                prune |= g.stats["max_radii"] > r.prune_screen
        n_prune = int(prune.sum())
        if n_prune and n_prune < len(g):
            g.keep(~prune)
        else:
            n_prune = 0
        for v in g.stats.values():
            v.zero_()
        return {"clone": n_clone, "split": n_split, "prune": n_prune}

    @torch.no_grad()
    def reset_opacities(self, g: GaussianParams) -> None:
        cap = math.log(self.reset_opacity / (1.0 - self.reset_opacity))
        g.params["logit_opacities"].data.clamp_(max=cap)
        g.zero_moments("logit_opacities")


def split_children(params: dict[str, torch.Tensor], sel: torch.Tensor, split_factor: float,
                   generator: Optional[torch.Generator]) -> dict[str, torch.Tensor]:
    """Two children per selected Gaussian (``[2K, ...]`` rows for every tensor, first children first).

    Children positions are sampled from the parent's Gaussian (offsets ``R (s * z)``,
    ``z ~ N(0, I)`` drawn from ``generator`` on the CPU), scales are the parent's divided
    by ``split_factor``; every other tensor is copied.
    """
    p = {k: v.data[sel] for k, v in params.items()}
    m = int(sel.sum())
    scales = torch.exp(p["log_scales"])
    noise = torch.randn(2, m, 3, generator=generator).to(scales.device, scales.dtype)
    offsets = torch.einsum("nij,bnj->bni", quat_to_rotmat(p["quats"]), noise * scales[None])
    out = {}
    for k, v in p.items():
        if k == "means":
            out[k] = (v[None] + offsets).reshape(2 * m, 3)
        elif k == "log_scales":
            out[k] = (v - math.log(split_factor)).repeat(2, 1)
        else:
            out[k] = v.repeat((2,) + (1,) * (v.ndim - 1))
    return out


# ----------------------------------------------------------------------------- MCMC
_QUAD_STEP = 0.045   # trapezoid step of relocation()'s integral (exponentially accurate: smooth, even integrand)
_QUAD_END = 7.2      # the integrand is below n * exp(-51) beyond


def relocation(opacities: torch.Tensor, scales: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scales of each of ``n`` Gaussians that replace one (3DGS-MCMC, eq. 9).

    ``n`` copies of opacity ``o'`` at one point composite to the original opacity when
    ``1 - (1 - o')^n = o``; their scales are the original's times ``o / D`` with
    ``D = sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)`` (the paper's
    choice, which keeps the copies' summed density close to the original's).

    Evaluation: summing over ``i`` first (``sum_i C(i-1, k) = C(n, k+1)``) gives
    ``D = sum_{m=1..n} (-1)^(m-1) C(n, m) o'^m / sqrt(m)``, an alternating sum that cancels
    catastrophically for large ``n`` and ``o'`` near 1; with
    ``1/sqrt(m) = (2/sqrt(pi)) int_0^inf exp(-m u^2) du`` it is the positive integral
    ``D = (2/sqrt(pi)) int_0^inf [1 - (1 - o' exp(-u^2))^n] du``, computed here in float64 by the
    trapezoid rule, accurate for any ``n``. ``n = 1`` gives back the inputs.
    Returns ``(new opacities [K], new scales [K, 3])``.
    """
    n = n.clamp_min(1).double()
    o = opacities.double()
    o_new = -torch.expm1(torch.log1p(-o.clamp(max=1.0)) / n)            # 1 - (1 - o)^(1/n)
    u = torch.arange(0.0, _QUAD_END, _QUAD_STEP, dtype=torch.float64, device=o.device)
    w = torch.full_like(u, _QUAD_STEP)
    w[0] = _QUAD_STEP / 2
    a = o_new[:, None] * torch.exp(-u * u)                               # [K, U]
    f = -torch.expm1(n[:, None] * torch.log1p(-a.clamp(max=1.0 - 1e-16)))
    denom = (2.0 / math.sqrt(math.pi)) * (f * w).sum(dim=1)
    coeff = torch.where(denom > 0, o / denom.clamp_min(1e-300), torch.ones_like(o))
    return o_new.to(opacities.dtype), scales * coeff.to(scales.dtype)[:, None]


@dataclass
class MCMCStrategy(Strategy):
    """3DGS as Markov chain Monte Carlo (Kheradmand et al. 2024), with ``max_gaussians`` as the budget.

    At each refinement: Gaussians with opacity at most ``prune_opacity`` are dead;
    each is moved onto a live Gaussian sampled with probability proportional to opacity
    (with replacement). A live Gaussian chosen ``n - 1`` times becomes ``n`` Gaussians
    (itself and its copies, every tensor copied) whose opacity and scales follow
    :func:`relocation`, so that together they render as it did. Then
    ``ceil(growth * N)`` new Gaussians (at most up to the budget) are added the
    same way, sampled from all Gaussians. Rows that were rewritten or added start with
    zero Adam moments.

    After every step (for the whole run) positions get Langevin noise
    ``noise_lr * lr_means * sigmoid(-k (o - t)) * Sigma z``, ``z ~ N(0, I)``, with
    ``k = 100``, ``t = 0.005`` (as the reference implementation's
    ``sigmoid(k (1 - o - 0.995))``: only nearly transparent Gaussians move far) and
    ``Sigma`` the Gaussian's covariance measured in units of the scene extent (so the
    noise is the paper's on a scene of extent 1, and the same in any world unit).

    Loss terms: ``opacity_reg * mean(opacity) + scale_reg * mean(scale / extent)`` (the
    L1 norms of the paper; scales in units of the extent).
    """

    prune_opacity: float = 0.005   # dead (relocated) at or below it
    growth: float = 0.05           # Gaussians added per refinement, fraction of the count
    noise_lr: float = 5e5          # position noise scale (times the position learning rate)
    opacity_reg: float = 0.01      # weight of mean(opacity) in the loss
    scale_reg: float = 0.01        # weight of mean(scale / extent) in the loss

    name: ClassVar[str] = "mcmc"
    budgeted: ClassVar[bool] = True
    reference: ClassVar[dict] = {"refine_start": 500, "refine_stop": 25_000, "refine_every": 100}
    recipe_defaults: ClassVar[dict] = {"init_opacity": 0.5, "init_scale": 0.1}
    noise_k: ClassVar[float] = 100.0
    noise_t: ClassVar[float] = 0.005

    def _make_generator(self, device: torch.device, seed: int) -> torch.Generator:
        # relocation sampling and the per-step noise draw on the Gaussians' device
        return torch.Generator(device=device).manual_seed(seed + 1)

    def regularizer(self, g: GaussianParams) -> Optional[torch.Tensor]:
        r = self
        terms = []
        if r.opacity_reg:
            terms.append(r.opacity_reg * torch.sigmoid(g.params["logit_opacities"]).mean())
        if r.scale_reg:
            terms.append(r.scale_reg / self.extent * torch.exp(g.params["log_scales"]).mean())
        return sum(terms) if terms else None

    def step(self, g: GaussianParams, step: int, lr_means: float) -> dict:
        info = {}
        if self.schedule.refines_at(step):
            info["refine"] = {"relocate": self.relocate(g), "add": self.add(g)}
        self.perturb(g, lr_means)
        return info

    def _sample(self, weights: torch.Tensor, k: int) -> torch.Tensor:
        return torch.multinomial(weights, k, replacement=True, generator=self.generator)

    @torch.no_grad()
    def _respawn(self, g: GaussianParams, src: torch.Tensor) -> dict[str, torch.Tensor]:
        """Share each sampled source with its copies: rewrite the sources' opacity and scales
        (:func:`relocation`, ``n`` = times sampled + 1) and return the copies' rows."""
        opac = torch.sigmoid(g.params["logit_opacities"].data[src])
        n = torch.bincount(src, minlength=len(g))[src] + 1
        o_new, s_new = relocation(opac, torch.exp(g.params["log_scales"].data[src]), n)
        eps = torch.finfo(o_new.dtype).eps
        o_new = o_new.clamp(self.prune_opacity, 1.0 - eps)
        g.assign(src, {"logit_opacities": torch.logit(o_new), "log_scales": torch.log(s_new)})
        return {k: v.data[src].clone() for k, v in g.params.items()}

    @torch.no_grad()
    def relocate(self, g: GaussianParams) -> int:
        opac = torch.sigmoid(g.params["logit_opacities"].data)
        dead = opac <= self.prune_opacity
        n_dead = int(dead.sum())
        if n_dead == 0 or n_dead == len(g):
            return 0
        alive = torch.nonzero(~dead)[:, 0]
        src = alive[self._sample(opac[alive], n_dead)]
        rows = self._respawn(g, src)
        g.assign(torch.nonzero(dead)[:, 0], rows)
        return n_dead

    @torch.no_grad()
    def add(self, g: GaussianParams) -> int:
        n = len(g)
        k = min(self.max_gaussians - n, math.ceil(self.growth * n))
        if k <= 0:
            return 0
        opac = torch.sigmoid(g.params["logit_opacities"].data)
        if float(opac.sum()) <= 0.0:
            return 0
        g.append(self._respawn(g, self._sample(opac, k)))
        return k

    @torch.no_grad()
    def perturb(self, g: GaussianParams, lr_means: float) -> None:
        p = g.params
        opac = torch.sigmoid(p["logit_opacities"].data)
        gate = torch.sigmoid(-self.noise_k * (opac - self.noise_t))
        var = torch.exp(2.0 * p["log_scales"].data) / self.extent ** 2         # [N, 3] in extent units
        R = quat_to_rotmat(p["quats"].data)
        z = torch.randn(p["means"].shape, generator=self.generator, device=g.device, dtype=p["means"].dtype)
        local = torch.einsum("nji,nj->ni", R, z) * var                          # S^2 R^T z
        noise = torch.einsum("nij,nj->ni", R, local)                            # R S^2 R^T z
        p["means"].data += (self.noise_lr * lr_means) * gate[:, None] * noise


STRATEGIES = {"default": DefaultStrategy, "mcmc": MCMCStrategy}


def make_strategy(strategy) -> Strategy:
    """A :class:`Strategy` from a name (``"default"``, ``"mcmc"``) or an instance (returned as is)."""
    if isinstance(strategy, Strategy):
        return strategy
    try:
        return STRATEGIES[str(strategy)]()
    except KeyError:
        raise InputError(f"unknown strategy {strategy!r}: choose one of {', '.join(STRATEGIES)}") from None
