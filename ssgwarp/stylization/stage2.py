"""Stage 2, Instance-level Style Transfer (run end to end by :mod:`ssgwarp.stylization.stylize`).

Stage 2 fine-tunes the Gaussians' colours so that renders along the training
cameras carry the style of the stylized key views (Stage 1), matched group by
group (:mod:`ssgwarp.stylization.matching`), or of the style image when Stage 1 did not run.

0. **colour transfer** (``pre``, ARF): one linear colour map per group, applied
   to the SH coefficients, gives the renders the colour mean and covariance of
   the targets (:func:`transfer_colors`, :mod:`ssgwarp.stylization.color`);
1. for ``iters`` steps, ``batch_size`` training views each (default one; the loss is their
   mean, Adam adapted by :func:`ssgwarp.core.optim.batch_factors`; under ``torchrun``
   each process renders its share, :mod:`ssgwarp.services.distributed`): render without gradient, treat
   the image as a leaf, compute the loss
   ``style_weight * L_style + content_weight * content + tv_weight * TV`` and
   its gradient ``dL/dimage``, render again with gradient and back-propagate
   ``dL/dimage`` through the rasterizer alone (*deferred back-propagation*: the
   feature network's graph and the rasterizer's are never held at once, so
   1008x756 views fit; gradients equal direct back-propagation, tested);
2. **colour transfer** again (``post``).

Losses (one view, image ``I``, render ``I0`` of the colour-transferred scene,
features ``phi`` = the extractor's layers concatenated at the coarsest resolution):
- style: NNFM (:meth:`ssgwarp.stylization.matching.MatchTargets.loss`, the paper's) or the
  sliced Wasserstein feature loss (:meth:`ssgwarp.stylization.matching.SlicedTargets.loss`),
  both with per-group matching; ``style_loss="auto"`` uses NNFM on VGG16
  features and SW on the weight-free random features (NNFM on random features
  collapses a view onto the style's dominant mode: docs/stylize.md);
- content: ``mean((phi(I) - phi(I0))^2) / mean(phi(I0)^2)`` (relative; weight by the extractor by default);
- TV: mean squared difference of neighbouring pixels; ``tv_weight=None`` (default): by the extractor
  (:func:`tv_weight_for`: 0.5 weight-free, measured in docs/stylize.md; 0.02 on VGG16).
- blend spread (``blend_weight``; default by the extractor, :func:`resolve_for` in
  :mod:`ssgwarp.stylization.feature_defaults`: 0.65 on the weight-free edge features, else 0): the weighted
  variance of the colours each pixel mixes (:mod:`ssgwarp.stylization.spread`; the view is then rendered
  with those channels too); empty-region term (``hold_empty``, :func:`ssgwarp.stylization.spread.empty_loss`);
  view-pair term (``consistency_weight``, :class:`ssgwarp.stylization.spread.ViewPairs`: the view against a
  neighbouring view warped into it, beyond ``consistency_budget`` x the starting scene's error).

Only colour is optimised (``sh_dc``); the higher SH bands are zeroed first by default (``sh_rest="zero"``:
view-independent stylized colour, docs/stylize.md; ``"keep"``, ``"optimise"``; ``free_opacity`` adds opacities);
every other tensor of the scene is passed through untouched (the same tensor
objects, bit-identical).

Modes: ``ist`` (default: per-group matching against the stylized key views),
``global`` (ARF: matching against the style image, one group), ``finetune``
(no IST: L1 + 0.2 D-SSIM against the stylized key views at the key cameras).
When Stage 1 could not run (no diffusion weights), ``ist`` and ``finetune``
fall back to global matching against the style image and the outputs say so.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch
import torch.nn.functional as F

from ..raster import rendering
from ..core.cameras import Cameras
from ..core.optim import adam
from ..errors import InputError
from ..services.distributed import SINGLE
from .feature_defaults import resolve_for, style_loss_kind, tv_weight_for
from ..services.loop import Diverged, Loop
from .batches import batch_size_for, batch_views, start_state
from .spread import SPREAD_CHANNELS, ViewPairs, blend_spread, check_pair_options, empty_loss, render_with_spread
from .matching import DEFAULT_CHUNK, MatchTargets, SlicedTargets, downsample_labels
from ..evaluation.features import content_loss
from ..core.optim import batch_factors
from ..raster.scene import GaussianScene

MODES = ("ist", "finetune", "global")
COLOR_TRANSFER = ("both", "pre", "post", "off")
COLOR_DETAIL = ("auto", "keep", "off")
SH_REST = ("keep", "zero", "optimise")
STYLE_LOSSES = ("auto", "nnfm", "sw")
BACKGROUNDS = ("transfer", "keep")


# ----------------------------------------------------------------------------- configuration
@dataclass
class Stage2Config:
    """Options of the Stage 2 optimisation (CLI flags of the same names).

    Attributes:
        mode: ``ist`` | ``finetune`` | ``global``.
        iters: optimisation steps (``batch_size`` training views each).
        lr: Adam learning rate of ``sh_dc`` (higher bands: ``lr / 20``; opacity logits: ``lr * 5``).
        style_weight, content_weight, tv_weight: loss weights; the last two ``None`` (default): by the extractor,
            content :func:`resolve_for` (0.01 on the patch features, whose content term holds the scene's own
            patterns, 0.05 on the others), TV :func:`tv_weight_for` (0.5 weight-free, 0.02 on VGG16).
        blend_weight: weight of the blend spread (:func:`ssgwarp.stylization.spread.blend_spread`; 0: off);
            ``None`` (default): by the extractor, :func:`resolve_for` (0.65 on the weight-free edge features,
            0 otherwise).
        style_loss: ``nnfm`` (nearest-neighbour feature matching, the paper's), ``sw`` (sliced
            Wasserstein between the feature distributions, :class:`ssgwarp.stylization.matching.SlicedTargets`) or
            ``auto``: NNFM on VGG16 features, SW on the weight-free random features (measured:
            docs/stylize.md).
        sw_projections: random directions per step of the ``sw`` loss.
        color_transfer: ARF's view-consistent colour transfer (:mod:`ssgwarp.stylization.color`) ``pre`` (before
            the optimisation), ``post`` (after it), ``both`` or ``off``.
        color_max_gain: the colour transfer's map may stretch colour differences by at most this
            factor (its largest eigenvalue; the consistency figures grow with it, see docs/stylize.md);
            ``None`` (default): by the extractor (1.0 on the weight-free edge features, 1.3 otherwise).
        color_detail: ``keep``: the colour transfer does not flatten the scene's lightness texture below
            the style's (nor raise it above the capture's own, nor any scale above the style's), by
            stretching its lightness output (:func:`ssgwarp.stylization.color.detail_gain`); ``off``: the
            plain mean-and-covariance map; ``auto`` (default): ``keep`` on the weight-free edge features,
            ``off`` otherwise.
        sh_rest: the higher SH bands (view-dependent colour): ``zero`` them at the start (default:
            renders become view-independent, lower consistency error at equal style distances,
            docs/stylize.md), ``keep`` them as reconstructed, or ``optimise`` them too.
        free_opacity: also optimise opacities (geometry otherwise frozen).
        densify, densify_views: split Gaussians where the style loss wants detail, at most ``densify x N`` new
            ones scored on ``densify_views`` views (0: off; run by ``stylize``, :mod:`ssgwarp.stylization.densify`).
        hold_empty: weight of the term keeping pixels the unstylized scene leaves empty as they were (no floaters).
        consistency_weight, consistency_neighbours: weight of the view-pair term
            (:class:`ssgwarp.stylization.spread.ViewPairs`: each step's view against one of its
            ``consistency_neighbours`` nearest training views, reprojected through the fixed depths; 0: off).
        background: the stylized scene's background colour: ``transfer`` (default) maps the capture's
            background by the same colour transfer as the scene (:func:`ssgwarp.stylization.color.transfer_background`;
            the optimisation renders over it and the run records it, ``metrics.json`` ``background``), so that
            the scene's outline keeps its contrast instead of, e.g., a darkened scene standing out against a
            white background (measured on the demo scene: docs/stylize.md); ``keep``: the capture's.
        label_mode: group maps to feature resolution by ``majority`` or ``nearest``.
        feature_scale: images are resized by this factor before the feature
            extractor (speed/accuracy knob; 1 = full resolution).
        style_scale: size of the style image against the views (its shorter side = ``style_scale`` x the views'
            shorter side, :func:`ssgwarp.core.imaging.fit_style`): above 1 the style's strokes and patterns are
            painted larger, below 1 smaller; ``"auto"``: :func:`ssgwarp.stylization.scale.auto_style_scale`.
            Without Stage 1 only (the stylized key views are views already).
        paint_strength: painting strength: the smoothing weights (``tv_weight``, ``blend_weight``) are divided by it;
            ``"auto"``: chosen per scene at the start of Stage 2 from the 3-D consistency probe
            (:func:`ssgwarp.stylization.spread.consistency_probe`, :func:`~ssgwarp.stylization.spread.strength_for`).
        region_check: without Stage 1, send a group whose style region is a poor match to the whole style
            (:func:`ssgwarp.stylization.regions.fall_back_poor_matches`; off: it costs the demo, docs/stylize.md).
        deferred: deferred back-propagation (False: direct, for comparison).
        chunk: similarity entries per block of the nearest-neighbour search.
        nn_precision: dtype of the nearest-neighbour search (``auto``: bf16 on CUDA, fp32 on CPU).
        checkpoint_every: iterations between checkpoints.
        seed: view order.
        batch_size: training views per step over all processes (None: one per process); the
            loss is their mean. batch_scaling: Adam for batches (``sqrt``: lr x sqrt(B), ``linear``:
            x B, both with betas ** B; ``none``), :func:`ssgwarp.core.optim.batch_factors`.
    """

    mode: str = "ist"
    iters: int = 600
    lr: float = 0.02
    style_weight: float = 1.0
    content_weight: Optional[float] = None
    tv_weight: Optional[float] = None
    blend_weight: Optional[float] = None
    style_loss: str = "auto"
    sw_projections: int = 64
    color_transfer: str = "both"
    color_max_gain: Optional[float] = None
    color_detail: str = "auto"
    sh_rest: str = "zero"
    free_opacity: bool = False
    densify: float = 0.0
    densify_views: int = 8
    hold_empty: float = 0.0
    consistency_weight: float = 0.0
    consistency_neighbours: int = 4
    consistency_budget: float = 2.0
    background: str = "transfer"
    label_mode: str = "majority"
    feature_scale: float = 1.0
    style_scale: float | str = 1.0
    paint_strength: float | str = 1.0
    region_check: bool = False
    deferred: bool = True
    chunk: int = DEFAULT_CHUNK
    nn_precision: str = "auto"
    checkpoint_every: int = 100
    seed: int = 0
    batch_size: Optional[int] = None
    batch_scaling: str = "sqrt"

    def validate(self) -> "Stage2Config":
        for key, allowed in (("mode", MODES), ("style_loss", STYLE_LOSSES), ("color_transfer", COLOR_TRANSFER),
                             ("color_detail", COLOR_DETAIL), ("background", BACKGROUNDS), ("sh_rest", SH_REST),
                             ("label_mode", ("majority", "nearest")), ("nn_precision", ("auto", "fp32", "bf16", "fp16")),
                             ("batch_scaling", ("sqrt", "linear", "none"))):
            if getattr(self, key) not in allowed:
                raise InputError(f"--{key.replace('_', '-')} {getattr(self, key)}: use one of {', '.join(allowed)}")
        if self.iters < 0:
            raise InputError(f"--iters {self.iters}: must be >= 0")
        for k in ("lr", "style_weight", "content_weight", "tv_weight", "blend_weight", "densify", "hold_empty",
                  "consistency_weight"):
            v = getattr(self, k)
            if v is None and k in ("content_weight", "tv_weight", "blend_weight"):
                continue
            if not math.isfinite(v) or v < 0:
                raise InputError(f"--{k.replace('_', '-')} {v}: must be a finite number >= 0")
        check_pair_options(self.consistency_budget, self.consistency_neighbours)
        if self.densify_views < 1:
            raise InputError(f"--densify-views {self.densify_views}: must be >= 1")
        if not 0 < self.feature_scale <= 4:
            raise InputError(f"--feature-scale {self.feature_scale}: must be in (0, 4]")
        for k, v in (("style-scale", self.style_scale), ("paint-strength", self.paint_strength)):
            if v != "auto" and not (isinstance(v, (int, float)) and math.isfinite(v) and 0.25 <= v <= 4):
                raise InputError(f"--{k} {v}: must be auto or in [0.25, 4] (1: as set)")
        if self.sw_projections < 1:
            raise InputError(f"--sw-projections {self.sw_projections}: must be >= 1")
        if self.color_max_gain is not None and not (math.isfinite(self.color_max_gain) and self.color_max_gain > 0):
            raise InputError(f"--color-max-gain {self.color_max_gain}: must be a finite number > 0")
        if self.chunk < 1:
            raise InputError(f"--chunk {self.chunk}: must be >= 1")
        if self.checkpoint_every < 1:
            raise InputError("--checkpoint-every must be >= 1")
        if self.batch_size is not None and self.batch_size < 1:
            raise InputError(f"--batch-size {self.batch_size}: must be >= 1")
        return self


# ----------------------------------------------------------------------------- rendering helpers
def render_rgb(scene: GaussianScene, cams: Cameras, background: Optional[torch.Tensor] = None,
               **kwargs) -> torch.Tensor:
    """``[C, H, W, 3]`` colour renders (background ``[3]`` blended behind by the rasterizer;
    differentiable, :func:`ssgwarp.raster.rendering.render`). The renders Stage 2 optimises, unclamped:
    :func:`ssgwarp.raster.rendering.render_views` composites and clamps, which the loss must not see."""
    bg = None
    if background is not None:
        bg = background.to(scene.device, scene.dtype).reshape(1, 3).expand(len(cams), 3)
    colors, _, _ = rendering.render(scene, cams.to(scene.device), backgrounds=bg, **kwargs)
    return colors[..., :3]


def render_batched(scene: GaussianScene, cams: Cameras, background: Optional[torch.Tensor] = None,
                   batch: int = 1, desc: Optional[str] = None) -> torch.Tensor:
    """No-grad renders of many cameras, a few at a time (on the scene's device): ``[C,H,W,3]``."""
    from ..core.progress import tqdm

    out = []
    with torch.no_grad():
        for s in tqdm(range(0, len(cams), batch), desc=desc, disable=desc is None, leave=False):
            out.append(render_rgb(scene, cams[list(range(s, min(s + batch, len(cams))))], background))
    return torch.cat(out, 0)


def render_alphas(scene: GaussianScene, cams: Cameras) -> torch.Tensor:
    """No-grad accumulated opacity ``[C, H, W]`` of many cameras, one at a time."""
    with torch.no_grad():
        return torch.cat([rendering.render(scene, cams[[c]].to(scene.device))[1][..., 0] for c in range(len(cams))])


def backward_views(render: Callable[[Cameras], torch.Tensor], cameras: Cameras,
                   loss_fns: Sequence[Callable[[torch.Tensor], torch.Tensor]], deferred: bool = True,
                   weight: float = 1.0) -> list[torch.Tensor]:
    """Back-propagate ``weight * sum_j loss_fns[j](render(cameras)[j])`` into the scene parameters.

    ``render``: cameras -> ``[C, h, w, 3]`` (differentiable in the parameters); all the cameras are
    rendered in one call. ``deferred`` (deferred back-propagation): the images are rendered
    without gradient, each view's ``dL/dimage`` is computed with its image as a leaf (the feature
    network's graph freed right after, one view at a time), then the images are rendered again
    with gradient and the stacked ``dL/dimage`` are pushed through the rasterizer alone; else the
    losses are back-propagated directly (reference). Returns each view's loss (detached);
    gradients are accumulated into the parameters' ``.grad``."""
    if not deferred:
        images = render(cameras)
        losses = [fn(images[j]) for j, fn in enumerate(loss_fns)]
        (weight * sum(losses)).backward()
        return [v.detach() for v in losses]
    with torch.no_grad():
        images = render(cameras)
    grads, values = [], []
    for j, fn in enumerate(loss_fns):
        image = images[j].detach().requires_grad_(True)
        value = fn(image)
        (grad,) = torch.autograd.grad(value, image)
        grads.append(grad if weight == 1.0 else grad * weight)
        values.append(value.detach())
    del images
    (render(cameras) * torch.stack(grads)).sum().backward()   # (= .backward(grads) to the bit, no sympy import)
    return values


def deferred_backward(render: Callable[[Cameras], torch.Tensor], camera: Cameras,
                      loss_fn: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Deferred back-propagation of ``loss_fn(render(camera))`` (one camera, image ``[H, W, 3]`` ->
    scalar) into the scene parameters (:func:`backward_views`); returns the loss (detached)."""
    return backward_views(render, camera, [loss_fn], deferred=True)[0]


def direct_backward(render: Callable[[Cameras], torch.Tensor], camera: Cameras,
                    loss_fn: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Plain back-propagation of ``loss_fn(render(camera))`` (reference for :func:`deferred_backward`)."""
    return backward_views(render, camera, [loss_fn], deferred=False)[0]


# ----------------------------------------------------------------------------- losses
def to_nchw(image: torch.Tensor) -> torch.Tensor:
    """``[H,W,3]`` or ``[B,H,W,3]`` -> ``[B,3,H,W]``."""
    return image.permute(2, 0, 1)[None] if image.ndim == 3 else image.permute(0, 3, 1, 2)


def extract(extractor, images: torch.Tensor, feature_scale: float = 1.0) -> torch.Tensor:
    """Stacked features ``[B, C, h, w]`` of images ``[B,H,W,3]`` / ``[H,W,3]`` (see :func:`stack_features`)."""
    from ..evaluation.features import stack_features

    x = to_nchw(images)
    if feature_scale != 1.0:
        size = (max(4, round(x.shape[-2] * feature_scale)), max(4, round(x.shape[-1] * feature_scale)))
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=feature_scale < 1)
    return stack_features(extractor(x))


def tv_loss(image: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of vertically and horizontally neighbouring pixels of ``[H,W,C]``."""
    return ((image[1:] - image[:-1]) ** 2).mean() + ((image[:, 1:] - image[:, :-1]) ** 2).mean()


def build_targets(extractor, images: torch.Tensor, labels: Optional[torch.Tensor], cfg: Stage2Config,
                  size: Optional[tuple[int, int]] = None):
    """Style targets from style images ``[V,H,W,3]`` (key views or the style image) and their
    group maps ``[V,H,W]`` (None = global): a :class:`~ssgwarp.stylization.matching.MatchTargets` (NNFM) or a
    :class:`~ssgwarp.stylization.matching.SlicedTargets` (SW), see :func:`style_loss_kind`. ``size`` resizes
    the images first (``(H, W)``)."""
    images = images.detach()
    if size is not None and tuple(images.shape[1:3]) != tuple(size):
        x = F.interpolate(to_nchw(images), size=size, mode="bilinear", align_corners=False, antialias=True)
        images = x.permute(0, 2, 3, 1)
        if labels is not None:
            labels = F.interpolate(labels[:, None].float(), size=size, mode="nearest")[:, 0].long()
    with torch.no_grad():
        feats = torch.cat([extract(extractor, images[v:v + 1], cfg.feature_scale) for v in range(len(images))])
    lab = None
    if labels is not None:
        lab = downsample_labels(labels.to(feats.device), tuple(feats.shape[-2:]), cfg.label_mode)
    if style_loss_kind(cfg, extractor) == "sw":
        return SlicedTargets(feats, lab, cfg.sw_projections, cfg.seed)
    return MatchTargets(feats, lab, cfg.chunk, cfg.nn_precision)


class ViewLoss:
    """The Stage 2 loss of one training view (``ist`` / ``global``).

    Args:
        extractor: a :class:`~ssgwarp.evaluation.features.FeatureExtractor`.
        targets: the style features to match.
        cfg: weights and knobs.
        view_labels: ``[C, H, W]`` group maps of the training views (None: global).
        originals: ``[C, H, W, 3]`` renders of the unstylized scene (content target).
        alphas: ``[C, H, W]`` their accumulated opacity (the empty-region term, ``cfg.hold_empty``).
        pairs: the view-pair term's geometry (``cfg.consistency_weight``; :meth:`ViewPairs.build`); :func:`optimise`
            gives it the current renders (``pairs.render``) and refuses ``consistency_weight > 0`` without it.
    """

    def __init__(self, extractor, targets: MatchTargets, cfg: Stage2Config,
                 view_labels: Optional[torch.Tensor] = None, originals: Optional[torch.Tensor] = None,
                 alphas: Optional[torch.Tensor] = None, pairs: Optional[ViewPairs] = None) -> None:
        cfg = resolve_for(cfg, extractor)
        self.extractor, self.targets, self.cfg = extractor, targets, cfg
        self.tv_weight = tv_weight_for(cfg, extractor)
        self.view_labels, self.originals, self.alphas = view_labels, originals, alphas
        if cfg.hold_empty > 0 and (originals is None or alphas is None):
            raise InputError("Stage 2 loss: hold_empty needs the original renders and their alphas")
        self.pairs: Optional[ViewPairs] = pairs
        self._labels: dict[int, torch.Tensor] = {}
        self.last: dict[str, float] = {}

    def labels_at(self, view: int, size: tuple[int, int]) -> Optional[torch.Tensor]:
        if self.view_labels is None or self.targets.labels is None:
            return None
        if view not in self._labels or tuple(self._labels[view].shape) != tuple(size):
            lab = self.view_labels[view:view + 1].to(self.targets.keys.device)
            self._labels[view] = downsample_labels(lab, size, self.cfg.label_mode)[0]
        return self._labels[view]

    def __call__(self, image: torch.Tensor, view: int, step: int = 0) -> torch.Tensor:
        cfg = self.cfg
        channels, image = image, image[..., :3]     # [..., 10] when rendered with the blend spread
        feats = extract(self.extractor, image, cfg.feature_scale)[0]      # [C,h,w]
        labels = self.labels_at(view, tuple(feats.shape[-2:]))
        if isinstance(self.targets, SlicedTargets):
            style = self.targets.loss(feats, labels, step=step)       # fresh projections each step
        else:
            style = self.targets.loss(feats, labels)
        total = cfg.style_weight * style
        parts = {"style": float(style.detach())}
        if self.originals is not None and cfg.content_weight > 0:
            with torch.no_grad():
                f0 = extract(self.extractor, self.originals[view].to(image.device), cfg.feature_scale)[0]
            content = content_loss([feats[None]], [f0[None]], relative=True)[0]
            total = total + cfg.content_weight * content
            parts["content"] = float(content.detach())
        if cfg.hold_empty > 0:
            hold = empty_loss(image, self.originals[view], self.alphas[view])
            total, parts["empty"] = total + cfg.hold_empty * hold, float(hold.detach())
        if cfg.consistency_weight > 0 and self.pairs is not None and self.pairs.render is not None:
            pair = self.pairs.term(image, view, step)   # (off until optimise renders the neighbours: densify)
            total, parts["pair"] = total + cfg.consistency_weight * pair, float(pair.detach())
        if self.tv_weight > 0:
            tv = tv_loss(image)
            total = total + self.tv_weight * tv
            parts["tv"] = float(tv.detach())
        if cfg.blend_weight > 0:
            if channels.shape[-1] != SPREAD_CHANNELS:
                raise ValueError(f"Stage 2 loss: blend_weight={cfg.blend_weight} needs the image rendered with the "
                                 f"blend spread ([..., {SPREAD_CHANNELS}] channels: spread.render_with_spread), got "
                                 f"[..., {channels.shape[-1]}]; render with it, or set blend_weight=0")
            spread = blend_spread(channels)
            total = total + cfg.blend_weight * spread
            parts["spread"] = float(spread.detach())
        parts["total"] = float(total.detach())
        self.last = parts
        return total


def finetune_loss(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``0.8 L1 + 0.2 (1 - SSIM)`` between ``[H,W,3]`` images (the 3DGS photometric loss)."""
    from ..services.losses import photometric

    return photometric(image[None], target[None])


# ----------------------------------------------------------------------------- parameters
def trainable_names(cfg: Stage2Config, scene: GaussianScene) -> list[str]:
    names = ["sh_dc"]
    if cfg.sh_rest == "optimise" and scene.sh_rest is not None:
        names.append("sh_rest")
    if cfg.free_opacity:
        names.append("logit_opacities")
    return names


def _lr(name: str, cfg: Stage2Config) -> float:
    return {"sh_dc": cfg.lr, "sh_rest": cfg.lr / 20.0, "logit_opacities": cfg.lr * 5.0}[name]


# ----------------------------------------------------------------------------- the optimisation
@dataclass
class Stage2Result:
    scene: GaussianScene
    history: list[dict] = field(default_factory=list)
    last: dict = field(default_factory=dict)
    seconds: float = 0.0
    iters_done: int = 0
    batch: dict = field(default_factory=dict)   # batch_size, world_size, scaling, lr_factor, betas


def _give_pairs_renders(loss: Optional[ViewLoss], draw: Callable[[Cameras], torch.Tensor]) -> None:
    """The view-pair term's neighbours rendered by ``draw`` with the current colours, without gradient."""
    if loss is not None and loss.cfg.consistency_weight > 0 and loss.pairs is None:
        raise InputError("Stage 2: consistency_weight needs the view pairs (ViewLoss(pairs=ViewPairs.build(...)))")
    if loss is not None and loss.pairs is not None:
        pairs = loss.pairs

        def render(view: int) -> torch.Tensor:
            with torch.no_grad():
                return draw(pairs.cameras[[view]])[0]
        pairs.render = render


def optimise(scene: GaussianScene, cameras: Cameras, cfg: Stage2Config, *,
             loss: Optional[ViewLoss] = None,
             finetune_images: Optional[torch.Tensor] = None, finetune_cameras: Optional[Cameras] = None,
             background: Optional[torch.Tensor] = None, checkpoint: Optional[Path] = None,
             resume: bool = False, progress: bool = True, log_every: int = 10,
             render_kwargs: Optional[dict] = None, group=None) -> Stage2Result:
    """Run Stage 2 and return the stylized scene.

    Args:
        scene: the reconstructed (grouped) scene; its tensors are not modified.
        cameras: the training cameras (``ist`` / ``global``).
        cfg: options (``cfg.batch_size`` views per step, their mean loss).
        loss: the per-view loss (``ist`` / ``global``).
        finetune_images, finetune_cameras: ``[V,H,W,3]`` stylized key views and their
            cameras (``finetune`` mode).
        background: ``[3]`` background colour.
        checkpoint: file to checkpoint into every ``cfg.checkpoint_every`` steps
            and on Ctrl-C; with ``resume`` the run continues from it (with any number of
            processes dividing its batch size).
        group: a :class:`ssgwarp.services.distributed.Group` when several processes optimise
            together: each renders its share of every batch, the gradients are averaged, Ctrl-C or
            a NaN on any process stops all at the same step, and only the main process writes the
            checkpoint and shows progress. Default: alone.
    """
    from ..core.fileio import atomic_path

    cfg.validate()
    group = group if group is not None else SINGLE
    finetune = cfg.mode == "finetune"
    if finetune and (finetune_images is None or finetune_cameras is None):
        raise InputError("finetune mode needs the stylized key views (Stage 1 output)")
    if not finetune and loss is None:
        raise InputError(f"{cfg.mode} mode needs a ViewLoss")
    batch = batch_size_for(cfg.batch_size, group)
    lr_factor, beta_power = batch_factors(batch, cfg.batch_scaling)
    betas = (0.9 ** beta_power, 0.999 ** beta_power)
    names = trainable_names(cfg, scene)
    if cfg.sh_rest == "zero" and scene.sh_rest is not None:
        scene = scene.replace(sh_rest=torch.zeros_like(scene.sh_rest))
    params = {n: getattr(scene, n).detach().clone().requires_grad_(True) for n in names}
    opt = adam([{"params": [p], "lr": _lr(n, cfg) * lr_factor, "name": n} for n, p in params.items()],
               eps=1e-15, betas=betas)
    start, history, elapsed = start_state(params, opt, checkpoint if resume else None, scene, cfg.mode, batch,
                                          group)
    info = {"batch_size": batch, "world_size": group.world_size, "scaling": cfg.batch_scaling,
            "lr_factor": lr_factor, "betas": list(betas)}

    def current() -> GaussianScene:
        return scene.replace(**params)

    rk = dict(render_kwargs or {})

    if cfg.blend_weight is None:    # left to the extractor: the loss knows it (finetune has no loss: no spread)
        cfg = replace(cfg, blend_weight=loss.cfg.blend_weight if loss is not None else 0.0)
    draw = render_with_spread if cfg.blend_weight > 0 and not finetune else render_rgb

    def render(cam: Cameras) -> torch.Tensor:
        return draw(current(), cam, background, **rk)

    _give_pairs_renders(loss, lambda cams: render_rgb(current(), cams, background, **rk))

    def save(step: int) -> None:
        if checkpoint is None or not group.is_main:
            return
        state = {"step": step, "params": {n: p.detach() for n, p in params.items()}, "params_names": names,
                 "optimizer": opt.state_dict(), "history": history, "seconds": elapsed + time.perf_counter() - t0,
                 "n": len(scene), "mode": cfg.mode, "config": asdict(cfg), "batch_size": batch,
                 "world_size": group.world_size}
        with atomic_path(checkpoint) as tmp:
            torch.save(state, tmp)

    n_views = len(finetune_cameras) if finetune else len(cameras)
    if n_views == 0:
        raise InputError("Stage 2: no views to optimise on")
    t0 = time.perf_counter()
    prog = {"done": start, "last": history[-1] if history else {}, "stop": False}

    def step_fn() -> dict:
        step = prog["done"]
        everyone = batch_views(step, batch, n_views, cfg.seed)
        views = group.share(everyone)   # this process's views of the step's batch
        opt.zero_grad(set_to_none=True)
        parts = _backward_share(render, views, step, cfg, loss, cameras, finetune_images, finetune_cameras,
                                scene, 1.0 / len(views))
        keys = sorted(parts[0])
        sums = [sum(p[k] for p in parts) for k in keys]
        finite = all(math.isfinite(p["total"]) for p in parts)
        # every process steps with the batch's mean gradient; NaN and Ctrl-C anywhere are seen everywhere
        flags = group.average_grads(list(params.values()), [0.0 if finite else 1.0,
                                                            1.0 if loop.stop_requested else 0.0] + sums)
        prog["stop"] = flags[1] > 0
        mean = {k: v / batch for k, v in zip(keys, flags[2:])}
        if flags[0] > 0:   # parameters untouched this step: the last good state is saved
            kept = (f"the state after the last good step ({step} steps) is saved to {checkpoint}"
                    if checkpoint is not None else "no checkpoint was asked for")
            where = f" on {int(flags[0])} of {group.world_size} processes" if group.active else ""
            raise Diverged(f"Stage 2: loss became {mean['total']} at step {step}{where}; last good checkpoint "
                           f"kept: {kept} (lower --lr and rerun with --resume)")
        opt.step()
        prog["done"] = step + 1
        prog["last"] = {"step": step, "view": everyone[0], **({"views": everyone} if batch > 1 else {}), **mean}
        if step % log_every == 0:
            history.append(prog["last"])
        return mean

    def on_step(parts: dict) -> None:
        loop.bar.set_postfix({k: f"{val:.4f}" for k, val in parts.items() if k in ("style", "total")})

    keep = (lambda: save(prog["done"])) if checkpoint is not None else None
    active = group.active
    loop = Loop(lambda: prog["done"], save=keep, every=cfg.checkpoint_every, save_last_good=keep,
                desc=f"stage 2 ({cfg.mode})", total=cfg.iters, progress=progress and group.is_main,
                sigterm=active, second_raises=not active, stop_agreed=(lambda: prog["stop"]) if active else None,
                after_stop=group.barrier, say=group.is_main)   # nobody leaves before the checkpoint is written
    loop.run(step_fn, cfg.iters, on_step)   # Ctrl-C: the step finishes, a checkpoint is written (ssgwarp.services.loop)
    last = prog["last"]
    seconds = elapsed + time.perf_counter() - t0
    out = scene.replace(**{n: p.detach().clone() for n, p in params.items()})
    return Stage2Result(out, history, last, seconds, cfg.iters, info)


def _backward_share(render, views: list[int], step: int, cfg: Stage2Config, loss, cameras, finetune_images,
                    finetune_cameras, scene: GaussianScene, weight: float) -> list[dict]:
    """Back-propagate ``weight`` x the summed losses of ``views``; each view's loss parts."""
    parts: list[dict] = []
    if cfg.mode == "finetune":
        def fit(v):
            target = finetune_images[v].to(scene.device, scene.dtype)
            return lambda img: finetune_loss(img, target)

        values = backward_views(render, finetune_cameras[views], [fit(v) for v in views], False, weight)
        return [{"total": float(x)} for x in values]

    def match(v):
        def fn(img):
            value = loss(img, v, step)
            parts.append({**loss.last, "total": float(value.detach())})   # (the value the gradient is of)
            return value
        return fn

    backward_views(render, cameras[views], [match(v) for v in views], cfg.deferred, weight)
    return parts
