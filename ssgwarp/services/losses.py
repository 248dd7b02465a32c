"""Image losses and quality measures shared by reconstruction, grouping and evaluation.

Images are ``[B, H, W, C]`` (channels last, as the rasterizer returns them)
unless said otherwise.
"""
from __future__ import annotations

from typing import Optional

import torch


def _nchw(img: torch.Tensor) -> torch.Tensor:
    return img.permute(0, 3, 1, 2) if img.ndim == 4 else img.permute(2, 0, 1)[None]


SSIM_SIGMA = 1.5  # the Gaussian window's standard deviation (Wang et al. 2004; kornia's and 3DGS's)
_WINDOWS: dict = {}  # (size, device, dtype) -> normalised 1-D Gaussian window (constants, made once)


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11) -> torch.Tensor:
    """Mean SSIM of two ``[B, H, W, C]`` (or ``[H, W, C]``) images in [0, 1] (Gaussian window 11,
    sigma 1.5, reflected borders). CUDA images: :func:`ssim_map` (the window made once per device,
    the five local moments filtered together, no host-device synchronisation); other devices:
    kornia's ``ssim``, the same map (its fused CPU path)."""
    x, y = _nchw(a), _nchw(b)
    if x.is_cuda:
        return ssim_map(x, y, window).mean()
    import kornia

    return kornia.metrics.ssim(x, y, window, max_val=1.0, padding="same").mean()


def gaussian_window(size: int, device, dtype) -> torch.Tensor:
    """The normalised 1-D Gaussian window (``SSIM_SIGMA``) of ``size`` taps, on ``device``; made in
    float64 on the host once per device and dtype (a window made per call would copy it to the
    device, and a blocking copy synchronises the stream)."""
    key = (int(size), torch.device(device), dtype)
    w = _WINDOWS.get(key)
    if w is None:
        x = torch.arange(size, dtype=torch.float64) - (size // 2)
        g = torch.exp(-x * x / (2.0 * SSIM_SIGMA ** 2))
        w = _WINDOWS[key] = (g / g.sum()).to(device=device, dtype=dtype)
    return w


def ssim_map(x: torch.Tensor, y: torch.Tensor, window: int = 11, eps: float = 1e-12) -> torch.Tensor:
    """SSIM map ``[B, C, H, W]`` of two ``[B, C, H, W]`` images in [0, 1]: local means, variances and
    covariance under the Gaussian window (separable, borders reflected), constants ``(0.01)^2`` and
    ``(0.03)^2``. The five moments are filtered as one stacked batch (one pad, two convolutions)."""
    if x.shape != y.shape or x.ndim != 4:
        raise ValueError(f"ssim_map: expected two [B, C, H, W] images of one shape, got {tuple(x.shape)} "
                         f"and {tuple(y.shape)}")
    dt = torch.promote_types(x.dtype, y.dtype)
    x, y = x.to(dt), y.to(dt)
    c = x.shape[1]
    w = gaussian_window(window, x.device, dt)
    p = window // 2
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    stack = torch.nn.functional.pad(stack, (p, p, p, p), mode="reflect")
    n = 5 * c
    stack = torch.nn.functional.conv2d(stack, w.view(1, 1, 1, window).expand(n, 1, 1, window), groups=n)
    stack = torch.nn.functional.conv2d(stack, w.view(1, 1, window, 1).expand(n, 1, window, 1), groups=n)
    mu1, mu2, s11, s22, s12 = stack.split(c, dim=1)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu12 = mu1 * mu2
    mu11, mu22 = mu1 * mu1, mu2 * mu2
    num = (2.0 * mu12 + c1) * (2.0 * (s12 - mu12) + c2)
    den = (mu11 + mu22 + c1) * ((s11 - mu11) + (s22 - mu22) + c2)
    return num / (den + eps)


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


def psnr(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """PSNR in dB of images ``[..., H, W, C]`` in [0, 1]; with ``mask [..., H, W]`` (1: counts) over the masked
    pixels only (their mean squared error)."""
    if mask is None:
        mse = torch.mean((a - b) ** 2)
    else:
        m = mask[..., None].to(a.dtype)
        mse = ((a - b) ** 2 * m).sum() / (m.sum() * a.shape[-1]).clamp_min(1.0)
    return -10.0 * torch.log10(mse.clamp_min(1e-20))


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()
