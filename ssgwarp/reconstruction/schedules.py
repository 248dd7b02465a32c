"""Schedules that fit the capture, for :class:`~ssgwarp.reconstruction.trainer.Trainer`.

* **Coarse-to-fine resolution** (after DashGaussian, Chen et al. 2025): early steps train on the images
  downsampled by a factor that falls from ``Recipe.res_start`` to 1 by step ``Recipe.res_until``, in
  geometric levels a factor sqrt(2) apart (:func:`resolution_factor`); each level's images are
  area-averaged from the full ones and its cameras are the full cameras rescaled
  (:meth:`ssgwarp.core.cameras.Cameras.rescaled`), cached one level at a time (:class:`Pyramid`).
* **Stopping when done** (``--iters auto``): the run is planned as the :data:`AUTO_MAX_ITERS`-step default
  (the same learning rates, densification and SH schedule); after densification ends and the images are
  at full resolution, the PSNR of a fixed handful of *training* views is measured every
  ``Recipe.stop_every`` steps (:class:`StopMonitor`); once it improved by less than ``Recipe.stop_tol`` dB
  over ``Recipe.stop_patience`` checks (:func:`plateaued`) the run ends after a tail of
  ``Recipe.stop_tail`` times the steps done, over which the position learning rate decays from its
  current value to the final one (:func:`tail_lr`). Held-out views never take part.
"""
from __future__ import annotations

import logging
import math
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")

AUTO = "auto"
AUTO_MAX_ITERS = 30_000   # the planned length (and the longest) of an --iters auto run: the 3DGS default


# ----------------------------------------------------------------------------- coarse-to-fine
def resolution_levels(start: float) -> list[float]:
    """Downsampling factors from ``start`` down to (not including) 1, a factor sqrt(2) apart
    (``start`` 4: 4, 2.83, 2, 1.41; 1 or less: none)."""
    if start <= 1.0:
        return []
    k = max(1, math.ceil(2.0 * math.log2(start) - 1e-9))
    return [start ** (1.0 - i / k) for i in range(k)]


def resolution_factor(step: int, start: float, until: int) -> float:
    """The downsampling factor of the images at (completed) ``step``: the levels of
    :func:`resolution_levels` in equal spans of ``[0, until)``, 1 from ``until`` on."""
    levels = resolution_levels(start)
    if not levels or step >= until:
        return 1.0
    return levels[min(len(levels) - 1, step * len(levels) // max(1, until))]


def level_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """The image size at downsampling ``factor``."""
    if factor <= 1.0:
        return int(width), int(height)
    return max(1, round(width / factor)), max(1, round(height / factor))


def downsample(images: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """``[C, H, W, K]`` images area-averaged to ``[C, height, width, K]`` (each output pixel the mean of
    the input pixels it covers)."""
    if images.shape[1:3] == (height, width):
        return images
    x = images.permute(0, 3, 1, 2)
    return F.interpolate(x, size=(height, width), mode="area").permute(0, 2, 3, 1).contiguous()


class Pyramid:
    """The training images, masks and cameras of one capture at one downsampling factor at a time
    (the level in use is kept; moving to another replaces it)."""

    def __init__(self, cameras: Cameras, images: torch.Tensor, masks: Optional[torch.Tensor] = None):
        self.cameras, self.images, self.masks = cameras, images, masks
        self.factor = 1.0
        self._level = (cameras, images, masks)

    @torch.no_grad()
    def level(self, factor: float) -> tuple[Cameras, torch.Tensor, Optional[torch.Tensor]]:
        """``(cameras, images [C, h, w, 3], masks [C, h, w] or None)`` at ``factor``."""
        if factor != self.factor:
            w, h = level_size(self.cameras.width, self.cameras.height, factor)
            if (w, h) == (self.cameras.width, self.cameras.height):
                self._level = (self.cameras, self.images, self.masks)
            else:
                masks = None if self.masks is None else downsample(self.masks[..., None], w, h)[..., 0]
                self._level = (self.cameras.rescaled(w, h), downsample(self.images, w, h), masks)
            self.factor = factor
        return self._level


def sh_degree_at(step: int, degree: int, recipe) -> int:
    """The SH degree rendered at ``step``: 0 before ``recipe.sh_start``, then one more every
    ``recipe.sh_interval`` steps up to ``degree`` (``sh_start == sh_interval``: ``step // sh_interval``)."""
    if step < recipe.sh_start:
        return 0
    return min(degree, 1 + (step - recipe.sh_start) // max(1, recipe.sh_interval))


# ----------------------------------------------------------------------------- stopping
def plateaued(values: Sequence[float], patience: int, tol: float) -> bool:
    """Whether the last ``patience`` of ``values`` (higher is better) improve on the best before them by
    less than ``tol``. False while there are ``patience`` values or fewer."""
    patience = max(1, int(patience))
    if len(values) <= patience:
        return False
    return max(values[-patience:]) - max(values[:-patience]) < tol


def tail_length(step: int, fraction: float, minimum: int) -> int:
    """The steps a run stopped at ``step`` trains on: ``fraction`` of the steps done, at least ``minimum``."""
    return max(int(minimum), round(fraction * step))


def tail_lr(step: int, start: int, stop: int, lr_start: float, lr_end: float) -> float:
    """The learning rate at ``step`` of a tail from ``start`` to ``stop``: exponential from ``lr_start``
    to ``lr_end``."""
    u = min(1.0, max(0.0, (step - start) / max(1, stop - start)))
    return math.exp(math.log(lr_start) * (1.0 - u) + math.log(lr_end) * u)


class StopMonitor:
    """The stop rule's state: the checks so far (``history``: ``[step, training-view PSNR]``) and,
    once decided, the step the plateau was seen (``decided``) and the step the run ends (``stop_at``).

    Checks are due every ``every`` steps from ``first`` (densification over, full resolution)."""

    def __init__(self, *, first: int, every: int, patience: int, tol: float, tail: float, horizon: int):
        self.first, self.every, self.patience, self.tol = int(first), max(1, int(every)), int(patience), float(tol)
        self.tail, self.horizon = float(tail), int(horizon)
        self.history: list[list[float]] = []
        self.decided: Optional[int] = None
        self.stop_at: Optional[int] = None

    def due(self, step: int) -> bool:
        return self.decided is None and step >= self.first and (step - self.first) % self.every == 0

    def add(self, step: int, value: float) -> bool:
        """Record a check; True when it decides the stop (``stop_at`` is then set)."""
        self.history.append([int(step), float(value)])
        if self.decided is None and plateaued([v for _, v in self.history], self.patience, self.tol):
            self.decided = int(step)
            self.stop_at = min(self.horizon, step + tail_length(step, self.tail, self.every))
            return True
        return False

    @property
    def end(self) -> int:
        return self.horizon if self.stop_at is None else self.stop_at

    def reason(self, step: int) -> str:
        if self.stop_at is not None and step >= self.stop_at:
            return (f"plateau: training-view PSNR rose < {self.tol:g} dB over {self.patience} checks "
                    f"{self.every} steps apart at step {self.decided}, then a tail of {self.stop_at - self.decided} steps")
        if step >= self.horizon:
            return f"no plateau before the longest run ({self.horizon} steps)"
        return "not finished"

    def state_dict(self) -> dict:
        return {"history": [list(h) for h in self.history], "decided": self.decided, "stop_at": self.stop_at}

    def load_state_dict(self, st: dict) -> None:
        self.history = [list(h) for h in st.get("history", [])]
        self.decided, self.stop_at = st.get("decided"), st.get("stop_at")


def check_views(train_ids: Sequence[int], n: int) -> list[int]:
    """``n`` training views evenly spaced in ``train_ids`` (all when there are fewer): the stop rule's."""
    ids = list(train_ids)
    if n >= len(ids):
        return ids
    return [ids[(2 * i + 1) * len(ids) // (2 * n)] for i in range(n)]


# ----------------------------------------------------------------------------- a run's schedules
class Schedules:
    """The schedules of one run (a resolved :class:`~ssgwarp.reconstruction.recipe.Recipe` on a capture ``data``
    of ``iters`` steps, ``auto``: the stop rule on, not before densification stops at ``refine_stop``): the
    images of each step, the position learning rate of the tail, the stop rule's checks and the record of it all."""

    def __init__(self, recipe, data, *, iters: int, auto: bool, refine_stop: int = 0):
        r = self.recipe = recipe
        self.iters, self.auto, self.names = int(iters), bool(auto), list(data.names)
        self.data = data
        self.pyramid = Pyramid(data.cameras, data.images, data.masks) if r.res_start > 1 else None
        self.monitor = None
        self.check_ids: list[int] = []
        if auto:
            self.monitor = StopMonitor(first=max(int(refine_stop or 0), r.res_until if self.pyramid else 0),
                                       every=r.stop_every, patience=r.stop_patience, tol=r.stop_tol,
                                       tail=r.stop_tail, horizon=self.iters)
            self.check_ids = check_views(data.train_ids, r.stop_views)

    @property
    def end(self) -> int:
        return self.iters if self.monitor is None else self.monitor.end

    def factor(self, step: int) -> float:
        """The training images' downsampling factor at ``step`` (1: full resolution)."""
        r = self.recipe
        return 1.0 if self.pyramid is None else resolution_factor(step, r.res_start, r.res_until)

    def views(self, step: int) -> tuple[Cameras, torch.Tensor, Optional[torch.Tensor]]:
        """``(cameras, images, masks)`` of the whole capture as trained at ``step``."""
        if self.pyramid is None:
            return self.data.cameras, self.data.images, self.data.masks
        return self.pyramid.level(self.factor(step))

    def means_lr(self, step: int, lr0: float, lr1: float) -> float:
        """The position learning rate at ``step``: log-linear from ``lr0`` to ``lr1`` over ``iters``, or,
        after a plateau, from where it was to ``lr1`` over the tail."""
        def planned(s: int) -> float:
            t = min(1.0, s / max(1, self.iters))
            return math.exp(math.log(lr0) * (1 - t) + math.log(lr1) * t)
        m = self.monitor
        if m is None or m.decided is None:
            return planned(step)
        return tail_lr(step, m.decided, m.stop_at, planned(m.decided), lr1)

    def check(self, step: int, psnr_of, loop=None) -> bool:
        """A check of the stop rule when one is due at ``step`` (``psnr_of(view ids)``: their mean PSNR);
        True when it decided the stop (then ``loop``'s progress bar, when given, shows the new end)."""
        m = self.monitor
        if m is None or not m.due(step) or not m.add(step, psnr_of(self.check_ids)):
            return False
        log.info("training-view PSNR stopped improving at step %d: ending at step %d", m.decided, m.stop_at)
        if loop is not None and loop.bar is not None:
            loop.bar.total = m.end
            loop.bar.refresh()
        return True

    def state_dict(self) -> Optional[dict]:
        return None if self.monitor is None else self.monitor.state_dict()

    def load_state_dict(self, st: Optional[dict]) -> None:
        if self.monitor is not None and st is not None:
            self.monitor.load_state_dict(st)

    def reason(self, step: int) -> str:
        if self.monitor is not None:
            return self.monitor.reason(step)
        return f"fixed length ({self.iters} steps)" if step >= self.iters else "not finished"

    def record(self, step: int) -> dict:
        """How long the run trained and why it stopped, and its schedules (``metrics.json``, ``data.json``)."""
        r = self.recipe
        out = {"iters": AUTO if self.auto else self.iters, "steps": int(step), "stopped": self.reason(step),
               "sh_start": r.sh_start, "sh_interval": r.sh_interval,
               "coarse_to_fine": None if self.pyramid is None else {"start": r.res_start, "until": r.res_until}}
        if self.monitor is not None:
            out["stop_rule"] = {"every": self.monitor.every, "patience": r.stop_patience, "tol_db": r.stop_tol,
                                "views": [self.names[i] for i in self.check_ids], "tail": r.stop_tail,
                                "decided_at": self.monitor.decided, "checks": self.monitor.history}
        return out
