"""Image feature extractors for style losses and metrics.

These extractors share one interface (:class:`FeatureExtractor`):

* **VGG16** (``vgg16:<layers>``): the 13 convolution layers of VGG16 written
  out by hand in torchvision's ``features`` layout, so a torchvision state dict
  (``features.N.weight`` / ``features.N.bias``, e.g. ``vgg16-397923af.pth``)
  loads as is. Inputs are ImageNet-normalised. The default layers are the
  conv3 block (relu3_1, relu3_2, relu3_3), as ARF's NNFM loss uses.
* **Random multi-scale** (``random-multiscale:seed<S>,c128s2``; with
  zero-mean first-layer filters and branches at 1/2, 1/4, 1/8,
  ``...,c128s2p2-4-8,edges``, ``random-edges``: the weight-free default of
  ``ssgwarp stylize`` when no VGG16 weights are found). Shallow
  convolutional networks with random filters followed by ReLU already produce
  feature statistics that capture texture (Ustyuzhaninov et al., "Texture
  synthesis using shallow convolutional networks with random filters", 2016;
  He et al., 2016) — as *distributions* (Gram or sliced Wasserstein losses);
  nearest-neighbour matching on them collapses onto the style's dominant mode
  (measured, docs/stylize.md). Three branches look at the image at full, 1/2
  and 1/4 resolution (receptive fields of about 5, 10 and 20 pixels), each two
  random 3x3 convolutions + ReLU (64 then 128 filters), pooled to 1/2
  resolution. (Until this version: 32/64 filters pooled to 1/4, like VGG's
  conv3 block — ``RandomMultiScale(channels=64, stride=4)``, named
  ``random-multiscale:seed<S>``.) Filters are drawn from a seeded CPU
  generator, so the extractor is identical for a seed on every machine and
  device.
* **Random strokes** (``random-strokes:...``, :class:`RandomStrokes`): deeper
  random networks with dilated convolutions (receptive fields to 124 px).
* **Pyramid patches** (``patches:p5s1-2-4``, :class:`PyramidPatches`): no
  network; the centred 5x5 windows of the image at full, 1/2 and 1/4
  resolution, matched as a distribution.

Every output that depends on features records :attr:`FeatureExtractor.name`.

Layers are named ``conv<b>_<i>`` / ``relu<b>_<i>`` / ``pool<b>``, a block
``conv<b>`` (= all ReLU outputs of block ``b``), or an integer index into
torchvision's ``features`` list.
"""
from __future__ import annotations

import os
from typing import Optional, Sequence, Union

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import InputError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# VGG16 configuration "D": output channels per conv, "M" = 2x2 max-pool.
VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M")


def _vgg16_layer_names() -> list[str]:
    """Names of the entries of torchvision's ``vgg16().features`` (31 entries)."""
    names, block, i = [], 1, 1
    for v in VGG16_CFG:
        if v == "M":
            names.append(f"pool{block}")
            block, i = block + 1, 1
        else:
            names += [f"conv{block}_{i}", f"relu{block}_{i}"]
            i += 1
    return names


VGG16_LAYERS = _vgg16_layer_names()
DEFAULT_LAYERS = ("conv3",)
LayerSpec = Union[str, int]


def resolve_layers(layers: Optional[Sequence[LayerSpec]]) -> list[int]:
    """Indices into the VGG16 ``features`` list for ``layers`` (block names expand to their ReLUs)."""
    layers = DEFAULT_LAYERS if layers is None else layers
    if isinstance(layers, (str, int)):
        layers = [layers]
    out: list[int] = []
    for spec in layers:
        if isinstance(spec, int) or (isinstance(spec, str) and spec.isdigit()):
            idx = int(spec)
            if not 0 <= idx < len(VGG16_LAYERS):
                raise InputError(f"VGG16 layer index {idx} out of range 0..{len(VGG16_LAYERS) - 1}")
            out.append(idx)
        elif spec in VGG16_LAYERS:
            out.append(VGG16_LAYERS.index(spec))
        elif isinstance(spec, str) and spec.startswith("conv") and "_" not in spec and spec[4:].isdigit():
            block = [i for i, n in enumerate(VGG16_LAYERS) if n.startswith(f"relu{spec[4:]}_")]
            if not block:
                raise InputError(f"VGG16 has no block '{spec}' (blocks conv1..conv5)")
            out += block
        else:
            raise InputError(f"unknown VGG16 layer '{spec}': use e.g. relu3_1, conv4_2, pool2, a block conv3, "
                             f"or an index 0..{len(VGG16_LAYERS) - 1}")
    return sorted(set(out))


def _layers_label(layers: Optional[Sequence[LayerSpec]]) -> str:
    layers = DEFAULT_LAYERS if layers is None else layers
    if isinstance(layers, (str, int)):
        layers = [layers]
    return "+".join(str(x) for x in layers)


class FeatureExtractor(nn.Module):
    """Base class: ``extractor(images [B,3,H,W] in [0,1]) -> list of [B,C_l,h_l,w_l]``.

    Attributes:
        name: what ran, e.g. ``"vgg16:conv3"`` or ``"random-multiscale:seed0,c128s2"``.
        strides: the downsampling factor of each returned layer.
    Parameters are frozen (``requires_grad=False``), but the call is
    differentiable with respect to the images.
    """

    name: str = "features"
    strides: list[int]

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError

    def _check(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise InputError(f"{self.name}: expected images [B,3,H,W], got {tuple(images.shape)}")
        p = next(self.parameters(), None)
        if p is None:
            p = next(self.buffers(), None)
        return images if p is None else images.to(device=p.device, dtype=p.dtype)

    @property
    def stride(self) -> int:
        """The coarsest stride among the returned layers (the resolution :func:`stack_features` uses)."""
        return max(self.strides)

    def freeze(self) -> "FeatureExtractor":
        for p in self.parameters():
            p.requires_grad_(False)
        return self.eval()


class _Normalize(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


class VGG16Features(FeatureExtractor):
    """VGG16 ``features`` (torchvision layout), truncated after the deepest requested layer."""

    def __init__(self, layers: Optional[Sequence[LayerSpec]] = None, normalize: bool = True) -> None:
        super().__init__()
        self.layer_ids = resolve_layers(layers)
        last = max(self.layer_ids)
        mods: list[nn.Module] = []
        cin = 3
        for v in VGG16_CFG:
            if v == "M":
                mods.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                mods += [nn.Conv2d(cin, v, kernel_size=3, padding=1), nn.ReLU(inplace=False)]
                cin = v
        # keep torchvision's indices (features.N) for the kept prefix
        self.features = nn.Sequential(*mods[: last + 1])
        self.normalize = _Normalize() if normalize else None
        self.name = f"vgg16:{_layers_label(layers)}"
        pools_before = [sum(1 for n in VGG16_LAYERS[: i + 1] if n.startswith("pool")) for i in self.layer_ids]
        self.strides = [2 ** p for p in pools_before]

    def load_torchvision(self, state: dict) -> "VGG16Features":
        """Load a torchvision VGG16 state dict (``features.N.*``; classifier keys are ignored)."""
        if "state_dict" in state and isinstance(state["state_dict"], dict):
            state = state["state_dict"]
        own = self.features.state_dict()
        picked = {}
        for k in own:
            full = f"features.{k}"
            if full not in state:
                raise InputError(f"VGG16 state dict lacks '{full}': expected a torchvision vgg16 state dict "
                                 f"(keys features.N.weight/bias)")
            t = state[full]
            if tuple(t.shape) != tuple(own[k].shape):
                raise InputError(f"VGG16 state dict '{full}' has shape {tuple(t.shape)}, expected "
                                 f"{tuple(own[k].shape)} (is it VGG16, not VGG11/13/19?)")
            picked[k] = t
        self.features.load_state_dict(picked)
        return self

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self._check(images)
        if self.normalize is not None:
            x = self.normalize(x)
        out = []
        want = set(self.layer_ids)
        for i, m in enumerate(self.features):
            x = m(x)
            if i in want:
                out.append(x)
        return out


def zero_mean_filters(w: torch.Tensor) -> torch.Tensor:
    """Conv filters ``w [out, in, k, k]`` with each ``k x k`` window's mean removed, rescaled to their norm."""
    z = w - w.mean(dim=(2, 3), keepdim=True)
    scale = w.flatten(1).norm(dim=1) / z.flatten(1).norm(dim=1).clamp_min(1e-12)
    return z * scale[:, None, None, None]


class RandomMultiScale(FeatureExtractor):
    """Seeded random shallow multi-scale conv features (weight-free; see module docs).

    Branch ``s`` (downsampling ``scales``, default 1, 2, 4): average-pool the normalised image by
    ``s``, two random 3x3 convolutions (``channels // 2`` then ``channels`` filters, He-normal
    weights) with ReLU, then adaptive average pooling to ``(H // stride, W // stride)``. Returns one
    ``[B, channels, H // stride, W // stride]`` tensor per branch.

    The defaults (128 channels, stride 2) were chosen by measurement for the sliced Wasserstein
    style loss (docs/stylize.md); ``RandomMultiScale(channels=64, stride=4)`` is the extractor of
    earlier versions.

    ``edges=True`` (``--extractor random-edges``, name suffix ``,edges``): each first-layer filter
    has its mean over the 3x3 window removed per input channel (its norm kept), so a flat colour
    gives the same response everywhere and the features follow edges and texture, not the colour
    itself (which the colour transfer matches). Measured (docs/stylize.md): much more texture,
    at a higher consistency error.
    """

    def __init__(self, seed: int = 0, channels: int = 128, scales: Sequence[int] = (1, 2, 4),
                 normalize: bool = True, stride: int = 2, edges: bool = False) -> None:
        super().__init__()
        if channels < 2 or stride < 1 or not scales:
            raise InputError(f"RandomMultiScale: channels >= 2, stride >= 1 and scales needed "
                             f"(got {channels}, {stride}, {scales})")
        self.seed, self.scales, self.out_stride = int(seed), tuple(int(s) for s in scales), int(stride)
        g = torch.Generator(device="cpu").manual_seed(self.seed)
        self.branches = nn.ModuleList()
        for _ in self.scales:
            c1 = nn.Conv2d(3, channels // 2, 3, padding=1, padding_mode="reflect")
            c2 = nn.Conv2d(channels // 2, channels, 3, padding=1, padding_mode="reflect")
            for c in (c1, c2):
                fan_in = c.weight[0].numel()
                with torch.no_grad():
                    c.weight.copy_(torch.randn(c.weight.shape, generator=g) * (2.0 / fan_in) ** 0.5)
                    c.bias.copy_(torch.randn(c.bias.shape, generator=g) * 0.05)
            if edges:
                with torch.no_grad():
                    c1.weight.copy_(zero_mean_filters(c1.weight))
            self.branches.append(nn.Sequential(c1, nn.ReLU(), c2, nn.ReLU()))
        self.normalize = _Normalize() if normalize else None
        parts = [f"seed{self.seed}"]
        if (channels, self.out_stride, self.scales) != (64, 4, (1, 2, 4)):
            parts.append(f"c{channels}s{self.out_stride}"
                         + ("" if self.scales == (1, 2, 4) else "p" + "-".join(map(str, self.scales))))
        if edges:
            parts.append("edges")
        self.name = "random-multiscale:" + ",".join(parts)
        self.strides = [self.out_stride] * len(self.scales)

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self._check(images)
        if self.normalize is not None:
            x = self.normalize(x)
        H, W = x.shape[-2:]
        size = (max(1, H // self.out_stride), max(1, W // self.out_stride))
        out = []
        for s, branch in zip(self.scales, self.branches):
            xs = F.avg_pool2d(x, s) if s > 1 and min(H, W) >= s else x
            out.append(F.adaptive_avg_pool2d(branch(xs), size))
        return out


class RandomStrokes(FeatureExtractor):
    """Seeded random *deep* features whose receptive fields cover brush strokes and patterns (weight-free).

    :class:`RandomMultiScale`'s branches see 5 x 5 pixels of their pyramid level: at 1/8 resolution that is
    40 px of the image, but blurred, so a stroke's shape (a thin curved line 20-60 px long, a tessera's
    outline) is not visible to any feature. Here every branch (pyramid level ``s`` in ``scales``, default
    1/2, 1/4) is a stack of random 3x3 convolutions with growing dilations ``dilations`` (default 1, 2, 4,
    8) and ReLU, ``channels`` filters each (the first zero-mean per window, as ``random-edges``: flat colour
    gives no signal), and *every* layer of the stack is returned, pooled to ``1 / stride``: layer ``j``
    of branch ``s`` sees ``s * (1 + 2 * sum(dilations[:j + 1]))`` pixels (3 ... 31 px at full
    resolution: 6 ... 62 px at 1/2, 12 ... 124 px at 1/4) at the level's resolution, so fine lines and their
    arrangement are both seen. Random multi-layer networks keep enough of an image's statistics to
    synthesize natural textures (Ustyuzhaninov et al., ICLR 2017); matched as distributions (the SW loss).

    Each layer's output is divided by a fixed scale measured once on a seeded noise image at
    construction, so every layer has unit mean square on natural-image-like input and no depth
    dominates the concatenated features. Name ``random-strokes:seed<S>,c<C>s<stride>p<scales>d<dilations>``.
    """

    def __init__(self, seed: int = 0, channels: int = 48, scales: Sequence[int] = (2, 4),
                 dilations: Sequence[int] = (1, 2, 4, 8), normalize: bool = True, stride: int = 2) -> None:
        super().__init__()
        if channels < 2 or stride < 1 or not scales or not dilations or min(dilations) < 1:
            raise InputError(f"RandomStrokes: channels >= 2, stride >= 1, scales and dilations >= 1 needed "
                             f"(got {channels}, {stride}, {scales}, {dilations})")
        self.seed, self.scales, self.out_stride = int(seed), tuple(int(s) for s in scales), int(stride)
        self.dilations = tuple(int(d) for d in dilations)
        g = torch.Generator(device="cpu").manual_seed(self.seed)
        self.branches = nn.ModuleList()
        for _ in self.scales:
            layers, cin = nn.ModuleList(), 3
            for j, d in enumerate(self.dilations):
                c = nn.Conv2d(cin, channels, 3, dilation=d)
                with torch.no_grad():
                    c.weight.copy_(torch.randn(c.weight.shape, generator=g) * (2.0 / c.weight[0].numel()) ** 0.5)
                    if j == 0:
                        c.weight.copy_(zero_mean_filters(c.weight))
                    c.bias.copy_(torch.randn(c.bias.shape, generator=g) * 0.05)
                layers.append(c)
                cin = channels
            self.branches.append(layers)
        self.normalize = _Normalize() if normalize else None
        self.register_buffer("gains", torch.ones(len(self.scales), len(self.dilations)))
        with torch.no_grad():   # unit mean square per layer on seeded 1/f-like noise
            noise = torch.randn(1, 3, 64, 64, generator=g)
            noise = sum(F.interpolate(F.avg_pool2d(noise, k), size=(64, 64), mode="bilinear", align_corners=False)
                        for k in (1, 2, 4, 8, 16)).clamp(-2, 2) * 0.25 + 0.5
            for b, ms in enumerate(self._raw(noise)):
                self.gains[b] = torch.stack([m.pow(2).mean().rsqrt() for m in ms])
        self.name = (f"random-strokes:seed{self.seed},c{channels}s{self.out_stride}p{'-'.join(map(str, self.scales))}"
                     f"d{'-'.join(map(str, self.dilations))}")
        self.strides = [self.out_stride] * (len(self.scales) * len(self.dilations))

    def _raw(self, x: torch.Tensor) -> list[list[torch.Tensor]]:
        if self.normalize is not None:
            x = self.normalize(x)
        H, W = x.shape[-2:]
        out = []
        for s, layers in zip(self.scales, self.branches):
            h = F.avg_pool2d(x, s) if s > 1 and min(H, W) >= 2 * s else x
            per = []
            for c in layers:   # replicate padding: valid at any size (reflect needs the pad below the size)
                d = c.dilation[0]
                h = F.relu(F.conv2d(F.pad(h, (d, d, d, d), mode="replicate"), c.weight, c.bias, dilation=d))
                per.append(h)
            out.append(per)
        return out

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self._check(images)
        H, W = x.shape[-2:]
        size = (max(1, H // self.out_stride), max(1, W // self.out_stride))
        return [F.adaptive_avg_pool2d(m, size) * self.gains[b, j]
                for b, ms in enumerate(self._raw(x)) for j, m in enumerate(ms)]


class PyramidPatches(FeatureExtractor):
    """Raw image patches on a pyramid, matched as a distribution (weight-free, no network).

    Level ``s`` of ``scales`` (default 1, 2, 4: full, 1/2 and 1/4 resolution, box-averaged) contributes every
    ``patch x patch`` window of the normalised image at that level (``3 * patch^2`` values), with each window's
    mean per colour channel removed (flat colour gives zeros, as ``random-edges``: the colour transfer matches
    colour), brought back to full resolution (nearest), so a pixel's feature is its own window at every
    level, fine to coarse (the parent-child vectors of pyramid texture synthesis, De Bonet 1997). Matched by
    the sliced Wasserstein loss, whose fresh random directions are fresh random linear filters over those
    windows at every step: the distribution of the style's patches, not of a fixed filter bank, is matched
    (patch-distribution texture synthesis: Elnekave & Weiss 2022). Name ``patches:p<patch>s<scales>``.
    """

    def __init__(self, patch: int = 5, scales: Sequence[int] = (1, 2, 4), normalize: bool = True) -> None:
        super().__init__()
        if patch < 2 or not scales or min(scales) < 1:
            raise InputError(f"PyramidPatches: patch >= 2 and scales >= 1 needed (got {patch}, {tuple(scales)})")
        self.patch, self.scales = int(patch), tuple(int(s) for s in scales)
        self.normalize = _Normalize() if normalize else None
        self.name = f"patches:p{self.patch}s{'-'.join(map(str, self.scales))}"
        self.strides = [1] * len(self.scales)

    def forward(self, images: torch.Tensor) -> list[torch.Tensor]:
        x = self._check(images)
        if self.normalize is not None:
            x = self.normalize(x)
        B, _, H, W = x.shape
        k, r = self.patch, self.patch // 2
        out = []
        for s in self.scales:
            xs = F.avg_pool2d(x, s) if s > 1 and min(H, W) >= 2 * s else x
            h, w = xs.shape[-2:]
            pad = (r, k - 1 - r, r, k - 1 - r)
            win = F.unfold(F.pad(xs, pad, mode="replicate"), k).reshape(B, 3, k * k, h, w)
            win = (win - win.mean(dim=2, keepdim=True)).reshape(B, 3 * k * k, h, w)
            out.append(win if (h, w) == (H, W) else F.interpolate(win, size=(H, W), mode="nearest"))
        return out


EXTRACTOR_KINDS = ("auto", "vgg16", "random", "random-edges", "random-strokes", "patches")
# branches of ``random-edges``: 1/2, 1/4, 1/8 (measured against 1, 1/2, 1/4 with the blend spread, docs/stylize.md:
# more texture and a lower consistency error on the demo scene, 25 styles)
EDGE_SCALES = (2, 4, 8)


def load_extractor(vgg_weights: Optional[str | os.PathLike] = None, device: torch.device | str = "cpu",
                   layers: Optional[Sequence[LayerSpec]] = None, *, kind: str = "auto", seed: int = 0,
                   config: Optional[dict] = None, normalize: bool = True,
                   fallback: str = "random") -> FeatureExtractor:
    """The feature extractor to use, frozen and on ``device``.

    ``kind``: ``"auto"`` (VGG16 when :mod:`ssgwarp.services.weights` finds or downloads
    the torchvision weights — explicit path, ``config``, ``SSGWARP_VGG16``,
    ``$SSGWARP_WEIGHTS``, the torch hub cache, else a download unless downloads
    are off — else the random extractor; a failed download says so in one line),
    ``"vgg16"`` (weights required: raises :class:`~ssgwarp.errors.WeightsNotFound`
    otherwise), ``"random"`` or ``"random-edges"`` (:class:`RandomMultiScale` with
    ``edges=True`` and branches at :data:`EDGE_SCALES`), ``"random-strokes"`` (:class:`RandomStrokes`) or
    ``"patches"`` (:class:`PyramidPatches`). ``layers`` applies to VGG16 (default the
    conv3 block); ``seed`` to the random extractor. ``fallback``: what ``"auto"`` gives without VGG16
    weights, ``"random"`` or ``"random-edges"`` (``ssgwarp stylize``'s weight-free default, measured:
    docs/stylize.md).
    """
    from ..services import weights

    if kind not in EXTRACTOR_KINDS:
        raise InputError(f"feature extractor kind '{kind}': use {', '.join(EXTRACTOR_KINDS)}")
    if fallback not in ("random", "random-edges", "random-strokes"):
        raise InputError(f"feature extractor fallback '{fallback}': use random, random-edges or random-strokes")
    path = None
    if kind == "vgg16":
        path = weights.require("vgg16", vgg_weights, config)
    elif kind == "auto":
        if vgg_weights and weights.find("vgg16", vgg_weights, config) is None:
            # an explicit path that does not exist is a user error, not a silent fallback
            raise InputError(weights.message("vgg16", vgg_weights))
        path = weights.obtain("vgg16", vgg_weights, config,
                              instead="features come from the weight-free random multi-scale extractor")
    if path is not None:
        ext = VGG16Features(layers, normalize=normalize)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # truncated / corrupt / wrong file
            raise weights.load_error("vgg16", path, e, "VGG16 state dict") from None
        ext.load_torchvision(state)
    elif kind == "random-strokes" or (kind == "auto" and fallback == "random-strokes"):
        ext = RandomStrokes(seed=seed, normalize=normalize)
    elif kind == "patches":
        ext = PyramidPatches(normalize=normalize)
    else:
        edges = kind == "random-edges" or (kind == "auto" and fallback == "random-edges")
        coarse = {"edges": True, "scales": EDGE_SCALES} if edges else {}
        ext = RandomMultiScale(seed=seed, normalize=normalize, **coarse)
    return ext.freeze().to(device)


def stack_features(feats: Sequence[torch.Tensor]) -> torch.Tensor:
    """Concatenate layers along channels at the coarsest resolution: ``[B, sum C_l, h, w]``.

    Finer layers are average-pooled (adaptive) to the smallest ``(h, w)``.
    """
    h = min(f.shape[-2] for f in feats)
    w = min(f.shape[-1] for f in feats)
    return torch.cat([f if f.shape[-2:] == (h, w) else F.adaptive_avg_pool2d(f, (h, w)) for f in feats], dim=1)


def gram_matrix(feat: torch.Tensor) -> torch.Tensor:
    """``[B, C, C]`` Gram matrix of ``feat [B,C,h,w]``, normalised by ``h*w``."""
    b, c, h, w = feat.shape
    f = feat.reshape(b, c, h * w)
    return f @ f.transpose(1, 2) / float(h * w)


def gram_loss(extractor: FeatureExtractor, images: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
    """``[B]`` Gram style loss: mean over layers of the mean squared Gram difference.

    images ``[B,3,H,W]``, style ``[1,3,Hs,Ws]`` (any size), both in [0,1].
    """
    fi = extractor(images)
    fs = extractor(style)
    per = [((gram_matrix(a) - gram_matrix(b)) ** 2).mean(dim=(1, 2)) for a, b in zip(fi, fs)]
    return torch.stack(per, 0).mean(0)


def content_loss(feats: Sequence[torch.Tensor], ref_feats: Sequence[torch.Tensor], *, relative: bool = False) -> torch.Tensor:
    """``[B]`` content loss: mean over layers of the mean squared feature difference (per layer
    ``[B, C, h, w]``). ``relative``: each layer's divided by the mean square of its reference
    features, ``mean((f - r)^2) / mean(r^2)``, so that a weight means the same for every extractor
    (Stage 2's content term, :class:`ssgwarp.stylization.stage2.ViewLoss`); the metric is absolute."""
    per = [((f - r) ** 2).mean(dim=(1, 2, 3)) for f, r in zip(feats, ref_feats)]
    if relative:
        per = [p / (r ** 2).mean(dim=(1, 2, 3)).clamp_min(1e-12) for p, r in zip(per, ref_feats)]
    return torch.stack(per, 0).mean(0)
