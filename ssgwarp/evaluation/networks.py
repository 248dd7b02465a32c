"""The pretrained networks the metrics use, written to their published state-dict layouts (weights
through :mod:`ssgwarp.services.weights`; never bundled):

* :class:`LPIPS` -- the LPIPS distance, VGG variant (VGG16 trunk from :mod:`ssgwarp.evaluation.features`,
  the lpips package's linear heads), :func:`load_lpips`;
* :class:`RAFTLarge` -- RAFT optical flow (Teed & Deng 2020) in torchvision's ``raft_large``
  layout, :func:`load_raft`, and :func:`estimate_flow` on ``[H, W, 3]`` images.

:mod:`ssgwarp.evaluation.metrics` re-exports them.
"""
from __future__ import annotations

import math
import os
import re
from typing import Mapping, Optional

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..services import weights
from ..errors import InputError
from .features import VGG16Features

Tensor = torch.Tensor

__all__ = ["LPIPS", "load_lpips", "RAFTLarge", "load_raft", "estimate_flow"]


# ----------------------------------------------------------------------------------------------
# LPIPS (VGG variant); weights through ssgwarp.services.weights
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
    """LPIPS from the ``ssgwarp.services.weights`` keys ``lpips`` (the lpips package's ``vgg.pth``) and ``vgg16``.

    Found or downloaded as :func:`ssgwarp.services.weights.require` does; raises WeightsNotFound.
    """
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
# RAFT (large), written to torchvision's raft_large state-dict layout; weights through ssgwarp.services.weights
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
    """RAFT-large from the torchvision state dict (``ssgwarp.services.weights`` key ``raft``: found, or downloaded
    into the torch hub cache unless downloads are off).

    Raises :class:`~ssgwarp.errors.WeightsNotFound` when the weights are neither here nor fetched,
    and :class:`~ssgwarp.errors.InputError` when the file is truncated, corrupt or not a raft_large state dict.
    """
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
