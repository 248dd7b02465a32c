"""Evaluation metrics: multi-view consistency, style / content losses, reconstruction quality.

Consistency (the short-/long-range protocol of the 3D style transfer papers):
a view A is warped into a view B and compared with B on the pixels both see.
Two warps are provided:

* :func:`reprojection_warp` (default, no weights): every pixel of B is lifted
  to 3D with B's rendered expected depth, projected into A and A's colour is
  sampled there (bilinear). The pixel is kept only where both renders are
  opaque (alpha >= ``alpha_min``), the point lands inside A, and the point's
  depth in A agrees with A's rendered depth within ``rel_tol`` (occlusion
  test: the surface B sees is the surface A sees). With exact geometry this is
  exact: a perfectly consistent scene gives 0.
* :func:`flow_warp`: A is forward-warped into B along an optical flow A→B by
  softmax splatting (Niklaus & Liu 2020; importance metric from brightness
  constancy), masking occlusions by a forward-backward flow check. The flow
  comes from RAFT (:class:`RAFTLarge`, torchvision ``raft_large`` state-dict
  layout; weights through :mod:`ssgwarp.weights`) to match the published protocol, or from the
  geometry (:func:`reprojection_flow`).

Errors on the mask are :func:`masked_rmse` (images in [0, 1]) and, when LPIPS
weights are configured, masked LPIPS (:class:`LPIPS`, both images multiplied by
the mask).

Quality: Gram-matrix style loss against the style image and feature content
loss against the unstylized renders (:func:`style_content_losses`) with any
:mod:`ssgwarp.features` extractor; PSNR / SSIM for reconstructions
(:func:`reconstruction_quality`).

Images are channels-last ``[H, W, C]`` float in [0, 1]; pixel centres are at
integer + 0.5 (the rasterizer's convention); cameras are world-to-camera
``viewmat [4, 4]`` and intrinsics ``K [3, 3]`` (OpenCV axes).
"""
from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from .errors import InputError

Tensor = torch.Tensor

__all__ = [
    "View", "WarpResult", "pixel_centers", "unproject", "project", "sample_bilinear",
    "reprojection_warp", "reprojection_flow", "softmax_splat", "flow_warp", "forward_backward_mask",
    "masked_rmse", "consistency_pairs", "LPIPS", "load_lpips", "RAFTLarge", "load_raft", "estimate_flow",
    "gram_style_loss", "content_loss", "style_content_losses", "fit_style", "reconstruction_quality",
    "projections", "wasserstein_1d_sorted", "sorted_projections", "sliced_wasserstein", "filter_responses",
    "texture_levels",
    "StyleDistance", "style_distances",
]


# ----------------------------------------------------------------------------------------------
# geometry
# ----------------------------------------------------------------------------------------------
@dataclass
class View:
    """One rendered view.

    Attributes:
        image: ``[H, W, C]`` colour in [0, 1].
        depth: ``[H, W]`` expected z-depth in camera space (the rasterizer's ``ED``).
        alpha: ``[H, W]`` accumulated opacity.
        viewmat: ``[4, 4]`` world-to-camera.
        K: ``[3, 3]`` intrinsics in pixels.
    """

    image: Tensor
    depth: Tensor
    alpha: Tensor
    viewmat: Tensor
    K: Tensor

    def __post_init__(self) -> None:
        H, W = self.image.shape[:2]
        if self.image.ndim != 3:
            raise InputError(f"View.image: expected [H, W, C], got {tuple(self.image.shape)}")
        for name in ("depth", "alpha"):
            t = getattr(self, name)
            if t.ndim == 3 and t.shape[-1] == 1:
                setattr(self, name, t[..., 0])
                t = getattr(self, name)
            if tuple(t.shape) != (H, W):
                raise InputError(f"View.{name}: expected [{H}, {W}], got {tuple(t.shape)}")


@dataclass
class WarpResult:
    """A view warped into another.

    Attributes:
        warped: ``[H_b, W_b, C]`` A's colours in B's frame (0 where unknown).
        mask: ``[H_b, W_b]`` bool, the pixels the comparison uses.
    """

    warped: Tensor
    mask: Tensor


def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """``[H, W, 2]`` (x, y) pixel-centre coordinates ``(j + 0.5, i + 0.5)``."""
    ys = torch.arange(height, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], dim=-1)


def unproject(depth: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """World points ``[H, W, 3]`` of the pixel centres at z-depth ``depth [H, W]``."""
    H, W = depth.shape
    uv = pixel_centers(H, W, depth.device, depth.dtype)
    K = K.to(depth)
    x = (uv[..., 0] - K[0, 2]) / K[0, 0] * depth
    y = (uv[..., 1] - K[1, 2]) / K[1, 1] * depth
    pc = torch.stack([x, y, depth], dim=-1)
    c2w = torch.linalg.inv(viewmat.to(depth))
    return pc @ c2w[:3, :3].T + c2w[:3, 3]


def project(points: Tensor, viewmat: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``[..., 2]`` and camera z ``[...]`` of world ``points [..., 3]``."""
    viewmat, K = viewmat.to(points), K.to(points)
    pc = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = pc[..., 2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    u = K[0, 0] * pc[..., 0] / zs + K[0, 2]
    v = K[1, 1] * pc[..., 1] / zs + K[1, 2]
    return torch.stack([u, v], dim=-1), z


def sample_bilinear(img: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples ``[..., C]`` of ``img [H, W, C]`` at pixel coordinates ``uv [..., 2]``.

    Pixel centres are at integer + 0.5; outside the image the border is repeated.
    """
    H, W, C = img.shape
    shape = uv.shape[:-1]
    g = uv.reshape(1, 1, -1, 2).to(img.dtype)
    grid = torch.stack([2.0 * g[..., 0] / W - 1.0, 2.0 * g[..., 1] / H - 1.0], dim=-1)
    grid = torch.nan_to_num(grid, nan=-2.0, posinf=2.0, neginf=-2.0)
    out = F.grid_sample(img.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0, :, 0].T.reshape(*shape, C)


def _inside(uv: Tensor, height: int, width: int) -> Tensor:
    """Points whose bilinear footprint lies on real pixels (centres span [0.5, size - 0.5])."""
    eps = 1e-4
    return ((uv[..., 0] >= 0.5 - eps) & (uv[..., 0] <= width - 0.5 + eps)
            & (uv[..., 1] >= 0.5 - eps) & (uv[..., 1] <= height - 0.5 + eps))


def reprojection_warp(a: View, b: View, *, rel_tol: float = 0.02, alpha_min: float = 0.9) -> WarpResult:
    """Warp view A into view B by exact reprojection (see module docs).

    For each pixel p of B: ``X = unproject(depth_b[p])``; ``(q, z) = project(X, A)``;
    ``warped[p] = image_a(q)`` (bilinear). ``mask[p]`` holds when ``alpha_b[p] >=
    alpha_min``, ``alpha_a(q) >= alpha_min``, q lies inside A, ``z > 0`` and
    ``|z - depth_a(q)| <= rel_tol * z`` (A sees the same surface: not occluded).
    """
    Hb, Wb = b.depth.shape
    Ha, Wa = a.depth.shape
    dt = torch.float64 if a.image.dtype == torch.float64 else torch.float32
    db = b.depth.to(dt)
    X = unproject(torch.nan_to_num(db, nan=0.0, posinf=0.0, neginf=0.0), b.K, b.viewmat)
    uv, z = project(X, a.viewmat, a.K)
    warped = sample_bilinear(a.image.to(dt), uv)
    da = sample_bilinear(a.depth.to(dt)[..., None], uv)[..., 0]
    aa = sample_bilinear(a.alpha.to(dt)[..., None], uv)[..., 0]
    ok_b = torch.isfinite(db) & (db > 0) & (b.alpha.to(dt) >= alpha_min)
    ok_a = _inside(uv, Ha, Wa) & (z > 0) & (aa >= alpha_min) & torch.isfinite(da) & (da > 0)
    visible = (z - da).abs() <= rel_tol * z.abs()
    mask = ok_b & ok_a & visible
    warped = torch.where(mask[..., None], warped, torch.zeros_like(warped))
    return WarpResult(warped.to(a.image.dtype), mask)


def reprojection_flow(a: View, b: View) -> tuple[Tensor, Tensor]:
    """Exact optical flow A→B from A's depth: ``flow [H_a, W_a, 2]`` (pixels) and B-camera depth ``[H_a, W_a]``.

    ``flow[p] = project(unproject(depth_a[p]), B) - p``; NaN where the depth is unusable.
    """
    Ha, Wa = a.depth.shape
    dt = torch.float64 if a.depth.dtype == torch.float64 else torch.float32
    da = a.depth.to(dt)
    ok = torch.isfinite(da) & (da > 0)
    X = unproject(torch.where(ok, da, torch.ones_like(da)), a.K, a.viewmat)
    uv, z = project(X, b.viewmat, b.K)
    flow = uv - pixel_centers(Ha, Wa, da.device, dt)
    bad = ~ok | (z <= 0)
    flow = torch.where(bad[..., None], torch.full_like(flow, float("nan")), flow)
    return flow, z


# ----------------------------------------------------------------------------------------------
# flow-based warp: softmax splatting
# ----------------------------------------------------------------------------------------------
def softmax_splat(image: Tensor, flow: Tensor, metric: Optional[Tensor] = None,
                  valid: Optional[Tensor] = None, size: Optional[tuple[int, int]] = None) -> tuple[Tensor, Tensor]:
    """Forward-warp ``image [H, W, C]`` along ``flow [H, W, 2]`` by softmax splatting.

    Each source pixel p lands at ``p + flow[p]`` and spreads over the 4 nearest
    target pixels with bilinear weights ``b``. A target q gets
    ``sum_p exp(Z_p) b_pq image_p / sum_p exp(Z_p) b_pq`` (``Z = metric [H, W]``,
    0 when None: average splatting). Sources where ``valid [H, W]`` is False or the
    flow is not finite are dropped. Computed with the per-target maximum of Z
    subtracted, so any metric range is stable.

    Returns ``(out [H_t, W_t, C], coverage [H_t, W_t])`` where coverage is the
    total bilinear weight received (1 for a hole-free one-to-one warp) and
    ``(H_t, W_t) = size`` (default ``(H, W)``).
    """
    H, W, C = image.shape
    Ht, Wt = size if size is not None else (H, W)
    dev = image.device
    dt = torch.float64 if image.dtype == torch.float64 else torch.float32
    img = image.to(dt).reshape(H * W, C)
    fl = flow.to(dt)
    ys, xs = torch.meshgrid(torch.arange(H, device=dev, dtype=dt), torch.arange(W, device=dev, dtype=dt), indexing="ij")
    tx, ty = xs + fl[..., 0], ys + fl[..., 1]
    ok = torch.isfinite(tx) & torch.isfinite(ty)
    if valid is not None:
        ok = ok & valid.to(torch.bool)
    Z = torch.zeros(H, W, dtype=dt, device=dev) if metric is None else metric.to(dt).reshape(H, W)
    ok = ok & torch.isfinite(Z)
    tx = torch.where(ok, tx, torch.zeros_like(tx))
    ty = torch.where(ok, ty, torch.zeros_like(ty))
    x0, y0 = torch.floor(tx), torch.floor(ty)
    fx, fy = tx - x0, ty - y0
    idx_l, w_l, src_l = [], [], []
    src = torch.arange(H * W, device=dev)
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi, yi = x0 + dx, y0 + dy
        keep = (ok & (w > 0) & (xi >= 0) & (xi <= Wt - 1) & (yi >= 0) & (yi <= Ht - 1)).reshape(-1)
        idx_l.append((yi * Wt + xi).reshape(-1)[keep].long())
        w_l.append(w.reshape(-1)[keep])
        src_l.append(src[keep])
    idx, w, s = torch.cat(idx_l), torch.cat(w_l), torch.cat(src_l)
    z = Z.reshape(-1)[s]
    zmax = torch.full((Ht * Wt,), -torch.inf, dtype=dt, device=dev).scatter_reduce(0, idx, z, "amax")
    e = torch.exp(z - zmax[idx]) * w
    num = torch.zeros(Ht * Wt, C, dtype=dt, device=dev).index_add_(0, idx, e[:, None] * img[s])
    den = torch.zeros(Ht * Wt, dtype=dt, device=dev).index_add_(0, idx, e)
    cov = torch.zeros(Ht * Wt, dtype=dt, device=dev).index_add_(0, idx, w)
    out = torch.where(den[:, None] > 0, num / den.clamp_min(torch.finfo(dt).tiny)[:, None], torch.zeros_like(num))
    return out.reshape(Ht, Wt, C).to(image.dtype), cov.reshape(Ht, Wt).to(image.dtype)


def forward_backward_mask(flow_ab: Tensor, flow_ba: Tensor, alpha1: float = 0.01, alpha2: float = 0.5) -> Tensor:
    """``[H, W]`` bool: pixels of A whose flow A→B is undone by the flow B→A (not occluded).

    Criterion of Sundaram et al. (2010): ``|f + g|^2 <= alpha1 (|f|^2 + |g|^2) + alpha2``
    with ``f = flow_ab[p]`` and ``g = flow_ba(p + f)`` (bilinear).
    """
    H, W = flow_ab.shape[:2]
    uv = pixel_centers(H, W, flow_ab.device, flow_ab.dtype) + torch.nan_to_num(flow_ab)
    g = sample_bilinear(torch.nan_to_num(flow_ba), uv)
    s = flow_ab + g
    lhs = (s * s).sum(-1)
    rhs = alpha1 * ((flow_ab * flow_ab).sum(-1) + (g * g).sum(-1)) + alpha2
    Hb, Wb = flow_ba.shape[:2]
    return (lhs <= rhs) & _inside(uv, Hb, Wb) & torch.isfinite(flow_ab).all(-1)


def flow_warp(image_a: Tensor, image_b: Tensor, flow_ab: Tensor, *, flow_ba: Optional[Tensor] = None,
              alpha_a: Optional[Tensor] = None, alpha_b: Optional[Tensor] = None, alpha_min: float = 0.9,
              metric_scale: float = -20.0, min_coverage: float = 0.5) -> WarpResult:
    """Forward-warp A into B along ``flow_ab [H, W, 2]`` by softmax splatting.

    Sources: A's pixels with ``alpha_a >= alpha_min`` (when given) and, when
    ``flow_ba`` is given, passing :func:`forward_backward_mask`. Importance
    metric ``Z = metric_scale * mean_c |image_a - image_b(p + flow_ab)|`` (brightness
    constancy: the better-matching source wins where several land). Mask: B
    pixels that received at least ``min_coverage`` bilinear weight and (when
    given) ``alpha_b >= alpha_min``.
    """
    H, W = image_a.shape[:2]
    valid = torch.isfinite(flow_ab).all(-1)
    if alpha_a is not None:
        valid = valid & (alpha_a.reshape(H, W) >= alpha_min)
    if flow_ba is not None:
        valid = valid & forward_backward_mask(flow_ab, flow_ba)
    uv = pixel_centers(H, W, image_a.device, image_a.dtype) + torch.nan_to_num(flow_ab).to(image_a.dtype)
    back = sample_bilinear(image_b.to(image_a.dtype), uv)
    metric = metric_scale * (image_a - back).abs().mean(-1)
    Hb, Wb = image_b.shape[:2]
    out, cov = softmax_splat(image_a, flow_ab, metric, valid, size=(Hb, Wb))
    mask = cov >= min_coverage
    if alpha_b is not None:
        mask = mask & (alpha_b.reshape(Hb, Wb) >= alpha_min)
    out = torch.where(mask[..., None], out, torch.zeros_like(out))
    return WarpResult(out, mask)


# ----------------------------------------------------------------------------------------------
# errors and pairs
# ----------------------------------------------------------------------------------------------
def masked_rmse(a: Tensor, b: Tensor, mask: Tensor) -> float:
    """Root mean squared error of ``a, b [H, W, C]`` over the pixels of ``mask [H, W]`` (all channels).

    NaN when the mask is empty.
    """
    m = mask.to(torch.bool)
    n = int(m.sum())
    if n == 0:
        return float("nan")
    d = (a.to(torch.float64) - b.to(torch.float64))[m]
    return float(torch.sqrt((d * d).mean()))


def consistency_pairs(num_views: int, kind: str = "short", gap: int = 7,
                      max_pairs: Optional[int] = None) -> list[tuple[int, int]]:
    """View index pairs ``(a, b)`` for the consistency protocol.

    ``short``: adjacent views ``(i, i + 1)``; ``long``: ``(i, i + gap)`` (gap
    clamped to ``num_views - 1``). At most ``max_pairs`` pairs, spread evenly
    over the sequence.
    """
    if kind not in ("short", "long"):
        raise InputError(f"consistency pairs: unknown kind '{kind}' (use short or long)")
    if num_views < 2:
        return []
    step = 1 if kind == "short" else max(1, min(int(gap), num_views - 1))
    pairs = [(i, i + step) for i in range(num_views - step)]
    if max_pairs is not None and 0 < max_pairs < len(pairs):
        picks = torch.linspace(0, len(pairs) - 1, max_pairs).round().long().unique().tolist()
        pairs = [pairs[i] for i in picks]
    return pairs


# ----------------------------------------------------------------------------------------------
# LPIPS (VGG variant); weights through ssgwarp.weights
# ----------------------------------------------------------------------------------------------
LPIPS_TAPS = (3, 8, 15, 22, 29)            # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 in VGG16.features
LPIPS_CHANNELS = (64, 128, 256, 512, 512)
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


class LPIPS(nn.Module):
    """LPIPS distance (VGG16 trunk, learned linear heads) of images ``[B, 3, H, W]`` in [0, 1].

    ``forward(x, y) -> [B]``: inputs mapped to [-1, 1] and shifted/scaled per
    channel, VGG16 ReLU outputs at 5 depths unit-normalised along channels,
    squared difference weighted by a 1x1 linear head, averaged over space, summed
    over depths. ``load(vgg_state, lin_state)`` takes a torchvision VGG16 state
    dict and the LPIPS ``vgg.pth`` heads (keys ``lin<k>.model.1.weight``).
    """

    name = "lpips-vgg"

    def __init__(self) -> None:
        super().__init__()
        from .features import VGG16Features

        self.trunk = VGG16Features(layers=list(LPIPS_TAPS), normalize=False)
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in LPIPS_CHANNELS])
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1))

    def load(self, vgg_state: Mapping[str, Tensor], lin_state: Mapping[str, Tensor]) -> "LPIPS":
        self.trunk.load_torchvision(dict(vgg_state))
        found = {}
        for k, v in lin_state.items():
            m = re.fullmatch(r"(?:net\.)?lin(\d)\.(?:model\.1\.)?weight", k)
            if m:
                found[int(m.group(1))] = v
        for i, lin in enumerate(self.lins):
            if i not in found:
                raise InputError(f"LPIPS weights lack 'lin{i}.model.1.weight': expected the lpips package's "
                                 f"VGG heads (vgg.pth)")
            w = found[i].reshape(lin.weight.shape) if found[i].numel() == lin.weight.numel() else None
            if w is None:
                raise InputError(f"LPIPS weights 'lin{i}' have shape {tuple(found[i].shape)}, expected "
                                 f"{tuple(lin.weight.shape)} (are they the VGG heads, not AlexNet/SqueezeNet?)")
            with torch.no_grad():
                lin.weight.copy_(w)
        return self

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        p = self.shift
        x = ((2.0 * x.to(p) - 1.0) - self.shift) / self.scale
        y = ((2.0 * y.to(p) - 1.0) - self.shift) / self.scale
        fx, fy = self.trunk(x), self.trunk(y)
        total = torch.zeros(x.shape[0], dtype=p.dtype, device=p.device)
        for a, b, lin in zip(fx, fy, self.lins):
            a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((a - b) ** 2).mean(dim=(1, 2, 3))
        return total


def load_lpips(lpips_weights: Optional[str | os.PathLike] = None, vgg_weights: Optional[str | os.PathLike] = None,
               device: torch.device | str = "cpu", config: Optional[Mapping[str, str]] = None) -> LPIPS:
    """LPIPS from the ``ssgwarp.weights`` keys ``lpips`` (the lpips package's ``vgg.pth``) and ``vgg16``.

    Found or downloaded as :func:`ssgwarp.weights.require` does; raises WeightsNotFound.
    """
    from . import weights

    lin_path = weights.require("lpips", lpips_weights, config)
    vgg_path = weights.require("vgg16", vgg_weights, config)
    states = []
    for key, path in (("vgg16", vgg_path), ("lpips", lin_path)):
        try:
            states.append(torch.load(path, map_location="cpu", weights_only=True))
        except Exception as e:  # truncated / corrupt / wrong file
            raise weights.load_error(key, path, e, "LPIPS weights" if key == "lpips" else "VGG16 state dict"
                                     ) from None
    model = LPIPS().load(*states)
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval().to(device)


# ----------------------------------------------------------------------------------------------
# RAFT (large), written to torchvision's raft_large state-dict layout; weights through ssgwarp.weights
# ----------------------------------------------------------------------------------------------
def _conv_block(cin: int, cout: int, k, stride: int = 1, norm: Optional[str] = None, relu: bool = True,
                padding=None) -> nn.Sequential:
    """conv (+ norm) (+ ReLU) as a Sequential, indices 0/1/2 as torchvision's Conv2dNormActivation."""
    if padding is None:
        padding = (k - 1) // 2 if isinstance(k, int) else tuple((x - 1) // 2 for x in k)
    mods: list[nn.Module] = [nn.Conv2d(cin, cout, k, stride=stride, padding=padding, bias=True)]
    if norm == "instance":
        mods.append(nn.InstanceNorm2d(cout))
    elif norm == "batch":
        mods.append(nn.BatchNorm2d(cout))
    if relu:
        mods.append(nn.ReLU())
    return nn.Sequential(*mods)


class _ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, norm: str, stride: int) -> None:
        super().__init__()
        self.convnormrelu1 = _conv_block(cin, cout, 3, stride, norm)
        self.convnormrelu2 = _conv_block(cout, cout, 3, 1, norm)
        self.downsample = _conv_block(cin, cout, 1, stride, norm, relu=False) if stride != 1 else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.downsample(x) + self.convnormrelu2(self.convnormrelu1(x)))


class _Encoder(nn.Module):
    """Feature / context encoder: 1/8 resolution, 256 channels."""

    def __init__(self, norm: str) -> None:
        super().__init__()
        self.convnormrelu = _conv_block(3, 64, 7, 2, norm)
        self.layer1 = nn.Sequential(_ResBlock(64, 64, norm, 1), _ResBlock(64, 64, norm, 1))
        self.layer2 = nn.Sequential(_ResBlock(64, 96, norm, 2), _ResBlock(96, 96, norm, 1))
        self.layer3 = nn.Sequential(_ResBlock(96, 128, norm, 2), _ResBlock(128, 128, norm, 1))
        self.conv = nn.Conv2d(128, 256, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(self.layer3(self.layer2(self.layer1(self.convnormrelu(x)))))


class _MotionEncoder(nn.Module):
    def __init__(self, corr_channels: int) -> None:
        super().__init__()
        self.convcorr1 = _conv_block(corr_channels, 256, 1)
        self.convcorr2 = _conv_block(256, 192, 3)
        self.convflow1 = _conv_block(2, 128, 7)
        self.convflow2 = _conv_block(128, 64, 3)
        self.conv = _conv_block(192 + 64, 126, 3)

    def forward(self, flow: Tensor, corr: Tensor) -> Tensor:
        c = self.convcorr2(self.convcorr1(corr))
        f = self.convflow2(self.convflow1(flow))
        return torch.cat([self.conv(torch.cat([c, f], 1)), flow], 1)


class _ConvGRU(nn.Module):
    def __init__(self, hidden: int, inp: int, k, pad) -> None:
        super().__init__()
        self.convz = nn.Conv2d(hidden + inp, hidden, k, padding=pad)
        self.convr = nn.Conv2d(hidden + inp, hidden, k, padding=pad)
        self.convq = nn.Conv2d(hidden + inp, hidden, k, padding=pad)

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        hx = torch.cat([h, x], 1)
        z = torch.sigmoid(self.convz(hx))
        r = torch.sigmoid(self.convr(hx))
        q = torch.tanh(self.convq(torch.cat([r * h, x], 1)))
        return h + z * (q - h)


class _Recurrent(nn.Module):
    def __init__(self, hidden: int, inp: int) -> None:
        super().__init__()
        self.convgru1 = _ConvGRU(hidden, inp, (1, 5), (0, 2))
        self.convgru2 = _ConvGRU(hidden, inp, (5, 1), (2, 0))

    def forward(self, h: Tensor, x: Tensor) -> Tensor:
        return self.convgru2(self.convgru1(h, x), x)


class _FlowHead(nn.Module):
    def __init__(self, cin: int, hidden: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, hidden, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden, 2, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2(F.relu(self.conv1(x)))


class _UpdateBlock(nn.Module):
    def __init__(self, corr_channels: int) -> None:
        super().__init__()
        self.motion_encoder = _MotionEncoder(corr_channels)
        self.recurrent_block = _Recurrent(128, 128 + 128)
        self.flow_head = _FlowHead(128, 256)


class _MaskPredictor(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.convrelu = _conv_block(128, 256, 3)
        self.conv = nn.Conv2d(256, 8 * 8 * 9, 1)

    def forward(self, h: Tensor) -> Tensor:
        return 0.25 * self.conv(self.convrelu(h))


class RAFTLarge(nn.Module):
    """RAFT optical flow (Teed & Deng 2020), "large" configuration.

    Written here (torchvision is not a dependency) with module names chosen so
    that a torchvision ``raft_large`` state dict (e.g.
    ``raft_large_C_T_SKHT_V2-ff5fadd5.pth``) loads with ``load_state_dict``:
    feature encoder with instance norm, context encoder with batch norm, 4-level
    all-pairs correlation pyramid with radius 4, ConvGRU update (1x5 then 5x1),
    convex 8x upsampling. ``forward(image1, image2 [B,3,H,W] in [-1, 1], H and W
    multiples of 8) -> flow [B, 2, H, W]`` (pixels, x then y) after ``iters`` updates.
    """

    levels, radius = 4, 4

    def __init__(self) -> None:
        super().__init__()
        corr_channels = self.levels * (2 * self.radius + 1) ** 2
        self.feature_encoder = _Encoder("instance")
        self.context_encoder = _Encoder("batch")
        self.update_block = _UpdateBlock(corr_channels)
        self.mask_predictor = _MaskPredictor()

    @staticmethod
    def _coords(b: int, h: int, w: int, device, dtype) -> Tensor:
        ys, xs = torch.meshgrid(torch.arange(h, device=device, dtype=dtype),
                                torch.arange(w, device=device, dtype=dtype), indexing="ij")
        return torch.stack([xs, ys], 0)[None].expand(b, 2, h, w)

    def _lookup(self, pyramid: list[Tensor], coords: Tensor) -> Tensor:
        b, _, h, w = coords.shape
        r = self.radius
        d = torch.arange(-r, r + 1, device=coords.device, dtype=coords.dtype)
        # channel order (i, j) -> x offset d[i], y offset d[j]
        off = torch.stack(torch.meshgrid(d, d, indexing="ij"), dim=-1).reshape(1, 2 * r + 1, 2 * r + 1, 2)
        cen = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
        out = []
        for lvl, vol in enumerate(pyramid):
            pts = cen / (2 ** lvl) + off
            hh, ww = vol.shape[-2:]
            gx = 2.0 * pts[..., 0] / max(ww - 1, 1) - 1.0
            gy = 2.0 * pts[..., 1] / max(hh - 1, 1) - 1.0
            s = F.grid_sample(vol, torch.stack([gx, gy], -1), mode="bilinear", align_corners=True)
            out.append(s.reshape(b, h, w, -1))
        return torch.cat(out, -1).permute(0, 3, 1, 2)

    @staticmethod
    def _upsample(flow: Tensor, mask: Tensor) -> Tensor:
        b, _, h, w = flow.shape
        m = torch.softmax(mask.reshape(b, 1, 9, 8, 8, h, w), dim=2)
        nb = F.unfold(8.0 * flow, kernel_size=3, padding=1).reshape(b, 2, 9, 1, 1, h, w)
        up = (m * nb).sum(2)                                 # [b, 2, 8, 8, h, w]
        return up.permute(0, 1, 4, 2, 5, 3).reshape(b, 2, 8 * h, 8 * w)

    def forward(self, image1: Tensor, image2: Tensor, iters: int = 12) -> Tensor:
        b, _, H, W = image1.shape
        if H % 8 or W % 8:
            raise InputError(f"RAFT: image size {W}x{H} must be a multiple of 8 (use estimate_flow, which pads)")
        f = self.feature_encoder(torch.cat([image1, image2], 0))
        f1, f2 = f[:b], f[b:]
        c, h, w = f1.shape[1:]
        corr = (f1.reshape(b, c, h * w).transpose(1, 2) @ f2.reshape(b, c, h * w)) / math.sqrt(c)
        vol = corr.reshape(b * h * w, 1, h, w)
        pyramid = [vol]
        for _ in range(self.levels - 1):
            vol = F.avg_pool2d(vol, 2, 2)
            pyramid.append(vol)
        ctx = self.context_encoder(image1)
        hidden, context = torch.tanh(ctx[:, :128]), F.relu(ctx[:, 128:])
        coords0 = self._coords(b, h, w, image1.device, image1.dtype)
        coords1 = coords0.clone()
        ub = self.update_block
        for _ in range(iters):
            coords1 = coords1.detach()
            cf = self._lookup(pyramid, coords1)
            motion = ub.motion_encoder(coords1 - coords0, cf)
            hidden = ub.recurrent_block(hidden, torch.cat([context, motion], 1))
            coords1 = coords1 + ub.flow_head(hidden)
        return self._upsample(coords1 - coords0, self.mask_predictor(hidden))


def load_raft(raft_weights: Optional[str | os.PathLike] = None, device: torch.device | str = "cpu",
              config: Optional[Mapping[str, str]] = None) -> RAFTLarge:
    """RAFT-large from the torchvision state dict (``ssgwarp.weights`` key ``raft``: found, or downloaded
    into the torch hub cache unless downloads are off).

    Raises :class:`~ssgwarp.errors.WeightsNotFound` when the weights are neither here nor fetched,
    and :class:`~ssgwarp.errors.InputError` when the file is truncated, corrupt or not a raft_large state dict.
    """
    from . import weights

    path = weights.require("raft", raft_weights, config)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise weights.load_error("raft", path, e, "RAFT state dict") from None
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    model = RAFTLarge()
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    extra = [k for k in state if k not in own]
    if missing or extra:
        raise InputError(f"{path}: not a torchvision raft_large state dict ({len(missing)} keys missing, e.g. "
                         f"{missing[:2]}; {len(extra)} unexpected, e.g. {extra[:2]})")
    for k, v in own.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise InputError(f"{path}: '{k}' has shape {tuple(state[k].shape)}, expected {tuple(v.shape)} "
                             f"(raft_small weights? use raft_large)")
    model.load_state_dict(state)
    for p in model.parameters():
        p.requires_grad_(False)
    return model.eval().to(device)


@torch.no_grad()
def estimate_flow(model: RAFTLarge, image1: Tensor, image2: Tensor, iters: int = 12) -> Tensor:
    """Optical flow ``[H, W, 2]`` from ``image1`` to ``image2`` (``[H, W, 3]`` in [0, 1]).

    Images are padded (replicate, bottom/right) to multiples of 8 and at least
    64 pixels, mapped to [-1, 1] as torchvision's RAFT transforms do, and the
    padding is cropped from the flow. RAFT is trained on images of 128 px and
    more: flows of smaller images are unreliable.
    """
    H, W = image1.shape[:2]
    p = next(model.parameters())
    x1 = image1.permute(2, 0, 1)[None].to(p) * 2.0 - 1.0
    x2 = image2.permute(2, 0, 1)[None].to(p) * 2.0 - 1.0
    # multiples of 8, and at least 64 so that the 4-level correlation pyramid exists
    ph, pw = max((-H) % 8, 64 - H), max((-W) % 8, 64 - W)
    if ph or pw:
        x1 = F.pad(x1, (0, pw, 0, ph), mode="replicate")
        x2 = F.pad(x2, (0, pw, 0, ph), mode="replicate")
    flow = model(x1, x2, iters=iters)[0, :, :H, :W]
    return flow.permute(1, 2, 0).to(image1.dtype)


# ----------------------------------------------------------------------------------------------
# style and content
# ----------------------------------------------------------------------------------------------
def fit_style(style: Tensor, height: int, width: int) -> Tensor:
    """Resize ``style [H_s, W_s, 3]`` so its shorter side equals ``min(height, width)`` (aspect kept): ``[1,3,h,w]``."""
    s = style.permute(2, 0, 1)[None]
    hs, ws = s.shape[-2:]
    k = min(height, width) / min(hs, ws)
    size = (max(1, round(hs * k)), max(1, round(ws * k)))
    if size == (hs, ws):
        return s
    return F.interpolate(s, size=size, mode="bilinear", align_corners=False, antialias=k < 1.0)


def gram_style_loss(feats: Sequence[Tensor], style_grams: Sequence[Tensor]) -> Tensor:
    """``[B]`` Gram style loss: mean over layers of ``mean_ij (G(f)_ij - S_ij)^2``.

    ``feats``: per layer ``[B, C, h, w]``; ``style_grams``: per layer ``[1, C, C]``
    (:func:`ssgwarp.features.gram_matrix`, normalised by ``h*w``).
    """
    from .features import gram_matrix

    per = [((gram_matrix(f) - s) ** 2).mean(dim=(1, 2)) for f, s in zip(feats, style_grams)]
    return torch.stack(per, 0).mean(0)


def content_loss(feats: Sequence[Tensor], ref_feats: Sequence[Tensor]) -> Tensor:
    """``[B]`` content loss: mean over layers of the mean squared feature difference."""
    per = [((f - r) ** 2).mean(dim=(1, 2, 3)) for f, r in zip(feats, ref_feats)]
    return torch.stack(per, 0).mean(0)


@torch.no_grad()
def style_content_losses(extractor, images: Tensor, style: Optional[Tensor] = None,
                         originals: Optional[Tensor] = None, batch: int = 4) -> dict[str, Tensor]:
    """Per-view Gram style and content losses.

    Args:
        extractor: ``ssgwarp.features`` extractor (``__call__([B,3,H,W]) -> list``).
        images: ``[V, H, W, 3]`` stylized renders.
        style: ``[H_s, W_s, 3]`` style image (resized by :func:`fit_style`) or None.
        originals: ``[V, H, W, 3]`` unstylized renders from the same cameras, or None.
    Returns:
        ``{"style": [V], "content": [V]}`` (keys present when computed).
    """
    V, H, W, _ = images.shape
    out: dict[str, list[Tensor]] = {}
    grams = None
    if style is not None:
        from .features import gram_matrix

        grams = [gram_matrix(f) for f in extractor(fit_style(style.to(images), H, W))]
    for s in range(0, V, batch):
        x = images[s:s + batch].permute(0, 3, 1, 2)
        fx = extractor(x)
        if grams is not None:
            out.setdefault("style", []).append(gram_style_loss(fx, grams).cpu())
        if originals is not None:
            fr = extractor(originals[s:s + batch].permute(0, 3, 1, 2).to(x))
            out.setdefault("content", []).append(content_loss(fx, fr).cpu())
    return {k: torch.cat(v) for k, v in out.items()}


# ----------------------------------------------------------------------------------------------
# weight-free style distances: sliced Wasserstein of colours (Lab) and of filter-bank responses
# ----------------------------------------------------------------------------------------------
SW_SEED = 0                 # the projections are drawn from this seed: every machine, every run, the same
COLOR_PROJECTIONS = 64      # 3 axes + 61 random directions in Lab
TEXTURE_PROJECTIONS = 32    # per pyramid level: 8 filter axes + 24 random directions
TEXTURE_LEVELS = 4          # at most 4 filter scales: sigma = 1, 2, 4, 8 px of the image ...
TEXTURE_MAX_SCALE = 1 / 16  # ... and at most this fraction of the image's shorter side (texture, not layout)
TEXTURE_ORIENTATIONS = 4    # 0, 45, 90, 135 degrees


def projections(dim: int, count: int, seed: int = SW_SEED, device=None, dtype=torch.float64) -> Tensor:
    """``[count, dim]`` unit directions: the ``dim`` coordinate axes, then seeded Gaussian-random directions."""
    count = max(count, dim)
    g = torch.Generator(device="cpu").manual_seed(int(seed))
    rnd = torch.randn(count - dim, dim, generator=g, dtype=torch.float64)
    d = torch.cat([torch.eye(dim, dtype=torch.float64), F.normalize(rnd, dim=1)])
    return d.to(device=device, dtype=dtype)


@functools.lru_cache(maxsize=16)
def _merged_quantiles(N: int, M: int, device: str) -> tuple[Tensor, Tensor, Tensor]:
    """Indices into sorted samples of sizes N and M, and the widths, of the intervals between the
    merged quantile breakpoints ``i/N`` and ``j/M`` (see :func:`wasserstein_1d_sorted`)."""
    tx = torch.arange(1, N + 1, dtype=torch.float64, device=device) / N
    ty = torch.arange(1, M + 1, dtype=torch.float64, device=device) / M
    t = torch.unique(torch.cat([tx, ty]))                     # sorted breakpoints, 1.0 last
    dt = torch.diff(t, prepend=t.new_zeros(1))
    mid = t - dt / 2
    return (torch.searchsorted(tx, mid).clamp_max(N - 1), torch.searchsorted(ty, mid).clamp_max(M - 1), dt)


def wasserstein_1d_sorted(xs: Tensor, ys: Tensor) -> Tensor:
    """Squared 2-Wasserstein distances ``[P]`` between 1-D empirical distributions, from sorted samples.

    ``xs [P, N]``, ``ys [P, M]`` sorted along the last axis (N and M may differ). Exact:
    ``W2^2 = int_0^1 (F^-1(t) - G^-1(t))^2 dt`` over the merged breakpoints ``i/N``, ``j/M``
    of the two step quantile functions.
    """
    N, M = xs.shape[-1], ys.shape[-1]
    if N == 0 or M == 0:
        raise InputError("sliced Wasserstein: an empty sample")
    if N == M:
        return ((xs.to(torch.float64) - ys.to(torch.float64)) ** 2).mean(-1)
    ix, iy, dt = _merged_quantiles(N, M, str(xs.device))
    d = xs[..., ix].to(torch.float64) - ys[..., iy].to(torch.float64)
    return (d * d * dt).sum(-1)


def sorted_projections(x: Tensor, num_projections: int, seed: int = SW_SEED) -> Tensor:
    """``[P, N]``: the points ``x [N, D]`` projected on the :func:`projections` directions, each row sorted."""
    if x.ndim != 2:
        raise InputError(f"sliced Wasserstein: expected points [N, D], got {tuple(x.shape)}")
    dirs = projections(x.shape[1], num_projections, seed, x.device, x.dtype)
    return (x @ dirs.T).T.sort(dim=-1).values


def sliced_wasserstein(x: Tensor, y: Tensor, num_projections: int = COLOR_PROJECTIONS, seed: int = SW_SEED,
                       y_sorted: Optional[Tensor] = None) -> Tensor:
    """Sliced 2-Wasserstein distance between point sets ``x [N, D]`` and ``y [M, D]`` (any N, M).

    ``SW = sqrt(mean_theta W2^2(<x, theta>, <y, theta>))`` over the directions of :func:`projections`
    (the D axes and seeded random ones), each 1-D distance exact (:func:`wasserstein_1d_sorted`).
    In the data's units; 0 for identical sets; for 1-D data the exact W2 (a shift by ``c`` gives ``|c|``).
    Invariant to the order of the points. ``y_sorted``: ``sorted_projections(y, ...)`` computed once
    for many ``x`` (then ``y`` is not used).
    """
    if x.ndim != 2 or (y_sorted is None and (y.ndim != 2 or x.shape[1] != y.shape[1])):
        raise InputError(f"sliced Wasserstein: expected [N, D] and [M, D], got {tuple(x.shape)}, "
                         f"{tuple(y.shape) if y is not None else None}")
    xs = sorted_projections(x, num_projections, seed)
    ys = sorted_projections(y.to(x), num_projections, seed) if y_sorted is None else y_sorted.to(xs)
    return torch.sqrt(wasserstein_1d_sorted(xs, ys).mean())


def _gaussian_derivative_bank(orientations: int = TEXTURE_ORIENTATIONS, sigma: float = 1.0,
                              dtype=torch.float32, device=None) -> Tensor:
    """``[2 * orientations, 1, k, k]`` scale-normalised first and second derivatives of a Gaussian.

    First order (edges): ``sigma * d/du G``; second order (bars, ridges): ``sigma^2 * d^2/du^2 G``,
    ``u`` the direction at angle ``pi * i / orientations``. Kernel radius ``ceil(4 sigma)``. Each
    first-order kernel sums to 0 and each second-order kernel is made to sum to 0 (a flat image
    responds with 0 exactly).
    """
    r = int(math.ceil(4 * sigma))
    ax = torch.arange(-r, r + 1, dtype=torch.float64)
    yy, xx = torch.meshgrid(ax, ax, indexing="ij")
    g = torch.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
    g = g / g.sum()
    first, second = [], []
    for i in range(orientations):
        th = math.pi * i / orientations
        u = xx * math.cos(th) + yy * math.sin(th)
        d1 = -(u / sigma ** 2) * g * sigma
        d2 = ((u ** 2 - sigma ** 2) / sigma ** 4) * g * sigma ** 2
        first.append(d1 - d1.mean())
        second.append(d2 - d2.mean())
    return torch.stack(first + second)[:, None].to(device=device, dtype=dtype)


def texture_levels(height: int, width: int, max_levels: int = TEXTURE_LEVELS) -> int:
    """Pyramid levels whose filter scale ``2^k`` px is at most ``TEXTURE_MAX_SCALE`` of the shorter side
    (at least 1, at most ``max_levels``): 4 levels from 128 px up, 3 at 64-127 px, 2 at 32-63 px.

    Coarser filters see the scene's layout (objects against the ground), not its texture: matching
    them to a style would mean moving the scene's structure, which Stage 2 must keep.
    """
    n = 1
    while n < max_levels and 2 ** n <= TEXTURE_MAX_SCALE * min(height, width):
        n += 1
    return n


def filter_responses(lightness: Tensor, levels: int = TEXTURE_LEVELS, orientations: int = TEXTURE_ORIENTATIONS,
                     mask: Optional[Tensor] = None) -> list[Tensor]:
    """Responses of the oriented derivative-of-Gaussian bank on a Gaussian pyramid.

    ``lightness [H, W]`` (Lab L). Level ``k`` is the image blurred (sigma 1, 5 taps) and halved ``k``
    times (filter scale ``2^k`` px of the input); at each level the bank of
    :func:`_gaussian_derivative_bank` (sigma 1 px, reflect padding). Returns per level
    ``[n_k, 2 * orientations]`` (pixels x filters): all ``h_k * w_k`` pixels, or with ``mask [H, W]``
    (bool) those whose pyramid cell is at least half inside the mask. Levels smaller than 8 px on a
    side, or with fewer than 16 masked pixels, are left out.
    """
    x = lightness[None, None]
    m = None if mask is None else mask.to(x.dtype)[None, None]
    bank = _gaussian_derivative_bank(orientations, 1.0, x.dtype, x.device)
    r = bank.shape[-1] // 2
    ax = torch.arange(-2, 3, dtype=x.dtype, device=x.device)
    g1 = torch.exp(-ax ** 2 / 2.0)
    g1 = g1 / g1.sum()

    def blur_halve(t: Tensor) -> Tensor:
        t = F.conv2d(F.pad(t, (2, 2, 2, 2), mode="replicate"), g1.view(1, 1, 1, 5))
        return F.conv2d(t, g1.view(1, 1, 5, 1))[..., ::2, ::2]

    out = []
    for k in range(levels):
        h, w = x.shape[-2:]
        if min(h, w) < 8:
            break
        mode = "reflect" if min(h, w) > r else "replicate"
        resp = F.conv2d(F.pad(x, (r, r, r, r), mode=mode), bank)[0]          # [F, h, w]
        resp = resp.reshape(resp.shape[0], -1).T
        if m is not None:
            resp = resp[m.reshape(-1) >= 0.5]
            if resp.shape[0] < 16:
                break
        out.append(resp)
        if k + 1 < levels:
            x = blur_halve(x)
            m = None if m is None else blur_halve(m)
    return out


class StyleDistance:
    """Weight-free distances of images to one style image: colour and texture (filter bank).

    * ``color``: :func:`sliced_wasserstein` between the images' pixel colours and the style's,
      in CIE Lab (:func:`ssgwarp.color.rgb_to_lab`; Lab units, about one just-noticeable difference per unit);
    * ``texture``: per pyramid level, the sliced Wasserstein distance between the per-pixel responses
      of a fixed oriented derivative-of-Gaussian filter bank (:func:`filter_responses`, on Lab L;
      4 orientations x first/second derivative), averaged over the levels (filter scales 1, 2, 4, 8 px,
      those up to 1/16 of the shorter image side: :func:`texture_levels`).

    The style image is resized like the Gram loss's (:func:`fit_style`: shorter side = the images'
    shorter side), so filter scales mean the same in both. No learned weights, no randomness beyond
    the seeded projections: the same images give the same numbers on every machine.

    ``StyleDistance(style [Hs, Ws, 3])(images [V, H, W, 3]) -> {"color": [V], "texture": [V]}``.
    """

    def __init__(self, style: Tensor, color_projections: int = COLOR_PROJECTIONS,
                 texture_projections: int = TEXTURE_PROJECTIONS, levels: Optional[int] = None,
                 seed: int = SW_SEED) -> None:
        if style.ndim != 3 or style.shape[-1] != 3:
            raise InputError(f"StyleDistance: expected a style image [H, W, 3], got {tuple(style.shape)}")
        self.style = style.detach().float()
        self.color_projections, self.texture_projections = color_projections, texture_projections
        self.levels, self.seed = levels, seed
        self._cache: dict[tuple[int, str], tuple[Tensor, list[Tensor]]] = {}

    def _features(self, image: Tensor, levels: int, mask: Optional[Tensor] = None) -> tuple[Tensor, list[Tensor]]:
        from .color import rgb_to_lab

        lab = rgb_to_lab(image.float())
        colors = lab.reshape(-1, 3) if mask is None else lab[mask]
        return colors, filter_responses(lab[..., 0], levels, mask=mask)

    def levels_for(self, height: int, width: int) -> int:
        """Pyramid levels used at this image size (``levels``, or :func:`texture_levels` when None)."""
        return self.levels if self.levels is not None else texture_levels(height, width)

    def _style_at(self, height: int, width: int, device) -> tuple[Tensor, list[Tensor]]:
        """The style's sorted projections (colour; texture per level) at the images' scale, cached."""
        key = (min(height, width), str(device))
        if key not in self._cache:
            s = fit_style(self.style.to(device), height, width)[0].permute(1, 2, 0)
            lab, resp = self._features(s, self.levels_for(height, width))
            self._cache[key] = (sorted_projections(lab, self.color_projections, self.seed),
                                [sorted_projections(r, self.texture_projections, self.seed) for r in resp])
        return self._cache[key]

    @torch.no_grad()
    def __call__(self, images: Tensor, alphas: Optional[Tensor] = None, alpha_min: float = 0.5) -> dict[str, Tensor]:
        """Distances of ``images [V, H, W, 3]`` (or one ``[H, W, 3]``) to the style.

        With ``alphas [V, H, W]`` only the scene's pixels (alpha >= ``alpha_min``) are compared: the
        background colour is not part of the scene (a view with fewer than 16 such pixels gives NaN).
        """
        if images.ndim == 3:
            images = images[None]
            alphas = None if alphas is None else alphas.reshape(1, *images.shape[1:3])
        V, H, W, _ = images.shape
        s_lab, s_resp = self._style_at(H, W, images.device)
        color, texture = [], []
        for v in range(V):
            mask = None if alphas is None else alphas[v].reshape(H, W).to(images.device) >= alpha_min
            if mask is not None and int(mask.sum()) < 16:
                color.append(float("nan"))
                texture.append(float("nan"))
                continue
            lab, resp = self._features(images[v], self.levels_for(H, W), mask)
            color.append(float(sliced_wasserstein(lab, None, self.color_projections, self.seed, s_lab)))
            per = [float(sliced_wasserstein(a, None, self.texture_projections, self.seed, b))
                   for a, b in zip(resp, s_resp)]
            texture.append(sum(per) / len(per) if per else float("nan"))
        return {"color": torch.tensor(color, dtype=torch.float64), "texture": torch.tensor(texture, dtype=torch.float64)}

    def mean(self, images: Tensor, alphas: Optional[Tensor] = None) -> dict[str, Optional[float]]:
        """``{"color", "texture"}`` averaged over the views (views without scene pixels skipped; None if none)."""
        out = {}
        for k, v in self(images, alphas).items():
            v = v[torch.isfinite(v)]
            out[k] = float(v.mean()) if v.numel() else None
        return out


def style_distances(images: Tensor, style: Tensor, alphas: Optional[Tensor] = None) -> dict[str, Tensor]:
    """Per-view weight-free style distances of ``images [V, H, W, 3]`` to ``style [Hs, Ws, 3]``
    (see :class:`StyleDistance`; ``alphas [V, H, W]``: compare the scene's pixels only)."""
    return StyleDistance(style)(images, alphas)


@torch.no_grad()
def reconstruction_quality(renders: Tensor, targets: Tensor) -> dict[str, list[float]]:
    """Per-image PSNR (dB) and SSIM of ``renders`` vs ``targets`` (``[V, H, W, 3]`` in [0, 1])."""
    from .losses import psnr, ssim

    if renders.shape != targets.shape:
        raise InputError(f"quality: renders {tuple(renders.shape)} and targets {tuple(targets.shape)} differ in shape")
    ps, ss = [], []
    for r, t in zip(renders, targets):
        r, t = r.clamp(0, 1)[None].float(), t[None].to(r.device).float()
        ps.append(float(psnr(r, t)))
        ss.append(float(ssim(r, t)))
    return {"psnr": ps, "ssim": ss}

