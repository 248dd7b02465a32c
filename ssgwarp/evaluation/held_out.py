"""The held-out views' scores of a reconstruction: PSNR / SSIM (and LPIPS when a model is given) per view
and their means, the ``psnr`` / ``ssim`` / ``lpips`` / ``per_view`` of a run's ``metrics.json``.

:func:`score_views` scores what a trainer renders (:meth:`ssgwarp.reconstruction.trainer.Trainer.evaluate`
gives it each view's render, target and mask: the whole image, or the half protocol of
:mod:`ssgwarp.reconstruction.appearance`); :func:`masked` is how a capture's masks take pixels out of both
(the scene's pixels: PSNR of their mean error, the rest 0 in both for SSIM), in the loss as in the scores.
"""
from __future__ import annotations

from typing import Iterable, Optional

import numpy as np
import torch

from ..services.losses import psnr, ssim

__all__ = ["masked", "score_views"]


def masked(img: torch.Tensor, gt: torch.Tensor, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``img``, ``gt`` with the pixels where ``masks [B, H, W]`` is 0 set to 0 in both (out of losses, metrics)."""
    return img * masks[..., None].to(img.dtype), gt * masks[..., None].to(gt.dtype)


@torch.no_grad()
def score_views(views: Iterable[tuple[str, torch.Tensor, torch.Tensor, Optional[torch.Tensor]]], lpips=None) -> dict:
    """Score ``(name, prediction [1, H, W, 3], target [1, H, W, 3], mask [1, H, W] or None)`` per view;
    returns ``{"views", "per_view": [{"name", "psnr", "ssim"(, "lpips")}], "psnr", "ssim", "lpips"}``
    (a mean is None when no view has it)."""
    per = []
    for name, pred, gt, mask in views:
        if mask is not None:
            pred, gt = masked(pred, gt, mask)
        row = {"name": name, "psnr": float(psnr(pred, gt, mask)), "ssim": float(ssim(pred, gt))}
        if lpips is not None:
            row["lpips"] = float(lpips(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2)).mean())
        per.append(row)
    out = {"views": len(per), "per_view": per}
    for k in ("psnr", "ssim", "lpips"):
        vals = [r[k] for r in per if k in r]
        out[k] = float(np.mean(vals)) if vals else None
    return out
