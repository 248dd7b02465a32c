"""What a training step of :class:`~ssgwarp.reconstruction.trainer.Trainer` hands around, made at the
least host cost (issue 40): its views (:class:`ViewCache`), the zero gradient of the SH bands it did not
render (:func:`zero_unrendered_grads`), its result (:class:`StepInfo`, whose MSE is made when read) and the
check of its loss (:class:`LossWatch`).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..core.optim import Adam
from ..raster import private_api as P


class ViewCache:
    """``cache(views, channels) -> (cameras, ground truth [B, H, W, 3], backgrounds [B, channels])`` of
    a capture's views, the backgrounds made once per shape. A one-view batch (the usual one) gets its
    cameras made once (indexing copies the index to the device every time) and its image as a view
    of the capture's (no copy); several views are indexed and stacked."""

    def __init__(self, data):
        self.data = data
        self.cameras: dict = {}
        self.factor = 1.0
        self.backgrounds: dict = {}

    def __call__(self, views: list[int], channels: int, level: Optional[tuple] = None, factor: float = 1.0) -> tuple:
        """``level``: ``(cameras, images, masks)`` to take the views from (default: the capture's), the
        ``factor`` they are downsampled by (the key of the cameras made once)."""
        cams, images = (self.data.cameras, self.data.images) if level is None else level[:2]
        key = (channels, len(views))
        bg = self.backgrounds.get(key)
        if bg is None:
            bg = self.backgrounds[key] = self.data.background_tensor(channels)[None].expand(len(views), -1).contiguous()
        if len(views) != 1:
            return cams[views], torch.stack([images[v] for v in views]), bg
        v = views[0]
        if factor != self.factor:  # a new resolution level: the cameras of the last one are not used again
            self.cameras, self.factor = {}, factor
        cam = self.cameras.get(v)
        if cam is None:
            cam = self.cameras[v] = cams[v]
        return cam, images[v:v + 1], bg


def zero_unrendered_grads(params: dict, with_ids: bool) -> None:
    """At SH degree 0 the colour renders from the DC term alone (no copy of all the coefficients),
    which leaves ``sh_rest`` without a gradient; it gets a zero one, as when all bands were rendered
    (its Adam state and step count then advance as before). The identity channels' path renders the
    DC term alone and has always left ``sh_rest`` out: unchanged (``with_ids``)."""
    p = params.get("sh_rest")
    if p is not None and p.grad is None and not with_ids:
        p.grad = torch.zeros_like(p)


class StepInfo(dict):
    """What :meth:`Trainer.train_step` returns: ``loss`` (a device scalar), what the strategy did
    (``refine``, ``reset``), and ``mse``, the step's mean squared error of the clamped render, made
    on the device the first time ``info["mse"]`` is read (the progress bar reads it every 10 steps;
    the others cost no kernels)."""

    def __init__(self, loss: torch.Tensor, img: Optional[torch.Tensor] = None, gt: Optional[torch.Tensor] = None):
        super().__init__(loss=loss)
        self.image_pair = None if img is None else (img, gt)  # (render, ground truth) until ``mse`` is made

    def __missing__(self, key):
        if key != "mse" or self.image_pair is None:
            raise KeyError(key)
        img, gt = self.image_pair
        self["mse"] = value = ((img.clamp(0, 1) - gt) ** 2).mean()
        self.image_pair = None
        return value

    def __contains__(self, key) -> bool:
        return super().__contains__(key) or (key == "mse" and self.image_pair is not None)

    def get(self, key, default=None):
        return self[key] if key in self else default


def adam_step(opt: torch.optim.Optimizer) -> None:
    """``opt.step()`` then ``opt.zero_grad(set_to_none=True)``. A fused torch Adam whose parameters all
    have their state (every step but the first) is stepped without the per-group Python of ``Adam.step``
    (about 1 ms of host time per step for the scene's six groups on the 2-core machine): the same
    ``torch._fused_adam_`` call per group, with the same arguments, so the same numbers to the bit
    (``ssgwarp.raster.private_api.fused_adam_step``, self-tested against ``Adam.step``). Anything else (hooks,
    another Adam variant, a first step) goes through ``opt.step()``. The optimizer and its state are torch's
    either way (checkpoints, densification's moment surgery)."""
    groups = P.fused_adam_groups(opt, (torch.optim.Adam, Adam))
    if groups is None:
        opt.step()
    elif groups:
        P.fused_adam_step(groups, getattr(opt, "found_inf", None))
    for group in opt.param_groups:
        for p in group["params"]:
            p.grad = None


class LossWatch:
    """The NaN check of a step's loss without a device synchronisation (one process, fused optimisers): the
    optimisers skip their update on the device when the loss is not finite (fused Adam's ``found_inf``, as
    torch's gradient scaler uses it: parameters, moments and step count unchanged), and the flag goes to the
    host with the step, read at the next step, checkpoint or end (:meth:`settle`)."""

    def __init__(self):
        # the loss flag of a step not read yet: (step, flag on the host or being copied there, CUDA event)
        self.pending = None
        self.host = None

    def watch(self, finite: torch.Tensor, opts: list, step: int, several: bool) -> bool:
        """Defer the check of step ``step``'s flag ``finite``. False: not possible here (``several``
        processes, whose flags travel with the gradients; an optimiser that is not fused); the caller reads
        the flag now."""
        if several or not all(o.defaults.get("fused") or getattr(o, "skips_found_inf", False) for o in opts):
            return False
        skip = (~finite).to(torch.float32)
        for o in opts:
            o.found_inf = skip
        event = None
        if finite.is_cuda:  # copied into pinned host memory behind the loss, an event marking it
            if self.host is None:
                self.host = torch.empty((), dtype=torch.bool, pin_memory=True)
            self.host.copy_(finite, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            finite = self.host
        self.pending = (step, finite, event)
        return True

    def settle(self) -> Optional[int]:
        """The step whose pending flag says its loss was NaN/inf (its updates were skipped), else None."""
        if self.pending is None:
            return None
        step, flag, event = self.pending
        self.pending = None
        if event is not None:
            event.synchronize()  # (the loss of that step: computed long before the next step reads it)
        return None if bool(flag) else step
