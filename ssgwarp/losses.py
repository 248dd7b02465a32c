"""Image losses and quality measures shared by reconstruction, grouping and evaluation.

Images are ``[B, H, W, C]`` (channels last, as the rasterizer returns them)
unless said otherwise.
"""
from __future__ import annotations

import torch


def _nchw(img: torch.Tensor) -> torch.Tensor:
    return img.permute(0, 3, 1, 2) if img.ndim == 4 else img.permute(2, 0, 1)[None]


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of two ``[B, H, W, C]`` (or ``[H, W, C]``) images in [0, 1] (kornia, gaussian window 11)."""
    import kornia

    return kornia.metrics.ssim(_nchw(a), _nchw(b), window, max_val=1.0, padding="same").mean()


def dssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Structural dissimilarity ``(1 - SSIM) / 2`` as used by the 3DGS loss."""
    return (1.0 - ssim(a, b)) / 2.0


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of images in [0, 1]."""
    mse = torch.mean((a - b) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(1e-20))


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()
