"""Image losses and quality measures shared by reconstruction, grouping and evaluation.

Images are ``[B, H, W, C]`` (channels last, as the rasterizer returns them)
unless said otherwise.
"""
from __future__ import annotations

from typing import Optional

import torch

try:  # the fused loss's Warp kernels; without warp-lang (or ssgwarp.kernels) the torch reference alone
    from ..raster.ssim_ops import photometric_warp
except ImportError:  # pragma: no cover - warp-lang or ssgwarp.kernels missing
    photometric_warp = None


def _nchw(img: torch.Tensor) -> torch.Tensor:
    return img.permute(0, 3, 1, 2) if img.ndim == 4 else img.permute(2, 0, 1)[None]


SSIM_SIGMA = 1.5  # the Gaussian window's standard deviation (Wang et al. 2004; kornia's and 3DGS's)
_WINDOWS: dict = {}  # (size, device, dtype) -> normalised 1-D Gaussian window (constants, made once)


def _fused(fused: Optional[bool], a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether the Warp kernels compute a loss: ``fused`` True (an error where they cannot), False
    (the torch reference), None: where they can (float32/float64 images on the CPU or CUDA)."""
    if fused is False:
        return False
    ok = (photometric_warp is not None and a.dtype in (torch.float32, torch.float64) and a.dtype == b.dtype
          and a.device.type in ("cpu", "cuda"))
    if fused and not ok:
        why = ("warp-lang (or ssgwarp.kernels) is not installed" if photometric_warp is None else
               f"{a.dtype}/{b.dtype} images on {a.device} (float32 or float64 on the CPU or CUDA)")
        raise ValueError(f"the fused loss cannot run: {why}; pass fused=False for the torch reference")
    return ok


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, fused: Optional[bool] = None) -> torch.Tensor:
    """Mean SSIM of two ``[B, H, W, C]`` (or ``[H, W, C]``) images in [0, 1] (Gaussian window 11,
    sigma 1.5, reflected borders). ``fused`` (default where it can run): the Warp kernels of
    :func:`photometric`'s fused form, in float64 whatever the images' precision (a metric: float32's
    rounding of the variances in flat regions moves SSIM by up to ~2e-5), the result in the images'
    dtype. Else, CUDA images and images narrower than the window's half: :func:`ssim_map` (the
    window made once per device, the five local moments filtered together, no host-device
    synchronisation); other devices: kornia's ``ssim``, the same map (its fused CPU path)."""
    if _fused(fused, a, b):
        w = gaussian_window(window, a.device, torch.float64)
        return photometric_warp(a.double(), b.double(), 0.0, 1.0, 0.0, w).to(a.dtype)
    x, y = _nchw(a), _nchw(b)
    if x.is_cuda or min(x.shape[-2:]) <= window // 2:
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
    if min(x.shape[-2:]) > p:
        stack = torch.nn.functional.pad(stack, (p, p, p, p), mode="reflect")
    else:  # narrower than the padding (torch's reflect pad refuses): reflected again and again, as numpy's
        rows, cols = _reflected(x.shape[-2], p, x.device), _reflected(x.shape[-1], p, x.device)
        stack = stack.index_select(2, rows).index_select(3, cols)
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


def _reflected(n: int, p: int, device) -> torch.Tensor:
    """The indices ``-p .. n - 1 + p`` of a line of ``n`` reflected into it (numpy's ``reflect``:
    period ``2 (n - 1)``; all 0 for ``n = 1``)."""
    j = torch.arange(-p, n + p, device=device)
    if n == 1:
        return torch.zeros_like(j)
    r = j.remainder(2 * (n - 1))
    return torch.where(r < n, r, 2 * (n - 1) - r)


def dssim(a: torch.Tensor, b: torch.Tensor, fused: Optional[bool] = None) -> torch.Tensor:
    """The D-SSIM term of the 3DGS loss: ``1 - SSIM`` (0 for equal images, up to 2)."""
    return 1.0 - ssim(a, b, fused=fused)


def photometric(a: torch.Tensor, b: torch.Tensor, lambda_dssim: float = 0.2,
                dssim_scale: float = 1.0, fused: Optional[bool] = None) -> torch.Tensor:
    """The 3DGS photometric loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` (Kerbl et al. 2023, lambda 0.2)
    of images ``[V, H, W, C]`` (the mean over views) or ``[H, W, C]``.

    ``dssim_scale`` multiplies the D-SSIM term: 0.5 reproduces the loss ssgwarp trained with before
    (``(1 - SSIM) / 2``), for comparisons only. ``fused`` (None: wherever it can run, float32/float64
    images on the CPU or CUDA; True: an error where it cannot; False: the torch reference, the spec):
    the Warp kernels of ``ssgwarp.raster.ssim_ops``, two launches forward and two backward instead of
    about 20 torch kernels each way, the same value and gradient to rounding (tests/test_fused_loss.py).
    """
    w_l1, w_dssim = 1.0 - lambda_dssim, lambda_dssim * dssim_scale
    if _fused(fused, a, b):
        return photometric_warp(a, b, w_l1, -w_dssim, w_dssim, gaussian_window(11, a.device, a.dtype))
    return w_l1 * l1(a, b) + w_dssim * dssim(a, b, fused=False)


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
