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
    """The D-SSIM term of the 3DGS loss: ``1 - SSIM`` (0 for equal images, up to 2)."""
    return 1.0 - ssim(a, b)


def photometric(a: torch.Tensor, b: torch.Tensor, lambda_dssim: float = 0.2,
                dssim_scale: float = 1.0) -> torch.Tensor:
    """The 3DGS photometric loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` (Kerbl et al. 2023, lambda 0.2).

    ``dssim_scale`` multiplies the D-SSIM term: 0.5 reproduces the loss ssgwarp trained with before
    (``(1 - SSIM) / 2``), for comparisons only.
    """
    return (1.0 - lambda_dssim) * l1(a, b) + (lambda_dssim * dssim_scale) * dssim(a, b)


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of images in [0, 1]."""
    mse = torch.mean((a - b) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(1e-20))


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()
