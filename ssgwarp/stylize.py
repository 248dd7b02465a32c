"""Stage 2, Instance-level Style Transfer, and the end-to-end ``ssgwarp stylize`` command.

Stage 2 fine-tunes the Gaussians' colours so that renders along the training
cameras carry the style of the stylized key views (Stage 1), matched group by
group (:mod:`ssgwarp.matching`), or of the style image when Stage 1 did not run.

0. **colour transfer** (``pre``, ARF): one linear colour map per group, applied
   to the SH coefficients, gives the renders the colour mean and covariance of
   the targets (:func:`transfer_colors`, :mod:`ssgwarp.color`);
1. for ``iters`` steps, one training view each: render without gradient, treat
   the image as a leaf, compute the loss
   ``style_weight * L_style + content_weight * content + tv_weight * TV`` and
   its gradient ``dL/dimage``, render again with gradient and back-propagate
   ``dL/dimage`` through the rasterizer alone (*deferred back-propagation*: the
   feature network's graph and the rasterizer's are never held at once, so
   1008x756 views fit; gradients equal direct back-propagation, tested);
2. **colour transfer** again (``post``).

Losses (one view, image ``I``, render ``I0`` of the colour-transferred scene,
features ``phi`` = the extractor's layers concatenated at the coarsest resolution):
- style: NNFM (:meth:`ssgwarp.matching.MatchTargets.loss`, the paper's) or the
  sliced Wasserstein feature loss (:meth:`ssgwarp.matching.SlicedTargets.loss`),
  both with per-group matching; ``style_loss="auto"`` uses NNFM on VGG16
  features and SW on the weight-free random features (NNFM on random features
  collapses a view onto the style's dominant mode: docs/stylize.md);
- content: ``mean((phi(I) - phi(I0))^2) / mean(phi(I0)^2)`` (relative, so the
  weight means the same for every extractor);
- TV: mean squared difference of neighbouring pixels.

Only colour is optimised (``sh_dc``); the higher SH bands are zeroed first by
default (``sh_rest="zero"``: view-independent stylized colour, measured in
docs/stylize.md; ``"keep"`` keeps them, ``"optimise"`` optimises them too;
``free_opacity`` adds the opacities);
every other tensor of the scene is passed through untouched (the same tensor
objects, bit-identical).

Modes: ``ist`` (default: per-group matching against the stylized key views),
``global`` (ARF: matching against the style image, one group), ``finetune``
(no IST: L1 + 0.2 D-SSIM against the stylized key views at the key cameras).
When Stage 1 could not run (no diffusion weights), ``ist`` and ``finetune``
fall back to global matching against the style image and the outputs say so.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch
import torch.nn.functional as F

from .cameras import Cameras
from .errors import InputError, SsgwarpError, WeightsNotFound
from .matching import DEFAULT_CHUNK, MatchTargets, SlicedTargets, downsample_labels
from .scene import GaussianScene

MODES = ("ist", "finetune", "global")
COLOR_TRANSFER = ("both", "pre", "post", "off")
SH_REST = ("keep", "zero", "optimise")
STYLE_LOSSES = ("auto", "nnfm", "sw")


# ----------------------------------------------------------------------------- configuration
@dataclass
class Stage2Config:
    """Options of the Stage 2 optimisation (CLI flags of the same names).

    Attributes:
        mode: ``ist`` | ``finetune`` | ``global``.
        iters: optimisation steps (one training view each).
        lr: Adam learning rate of ``sh_dc`` (higher bands: ``lr / 20``; opacity logits: ``lr * 5``).
        style_weight, content_weight, tv_weight: loss weights.
        style_loss: ``nnfm`` (nearest-neighbour feature matching, the paper's), ``sw`` (sliced
            Wasserstein between the feature distributions, :class:`ssgwarp.matching.SlicedTargets`) or
            ``auto``: NNFM on VGG16 features, SW on the weight-free random features (measured:
            docs/stylize.md).
        sw_projections: random directions per step of the ``sw`` loss.
        color_transfer: ARF's view-consistent colour transfer (:mod:`ssgwarp.color`) ``pre`` (before
            the optimisation), ``post`` (after it), ``both`` or ``off``.
        color_max_gain: the colour transfer's map may stretch colour differences by at most this
            factor (its largest eigenvalue; the consistency figures grow with it, see docs/stylize.md).
        sh_rest: the higher SH bands (view-dependent colour): ``zero`` them at the start (default:
            renders become view-independent, lower consistency error at equal style distances,
            docs/stylize.md), ``keep`` them as reconstructed, or ``optimise`` them too.
        free_opacity: also optimise opacities (geometry otherwise frozen).
        label_mode: group maps to feature resolution by ``majority`` or ``nearest``.
        feature_scale: images are resized by this factor before the feature
            extractor (speed/accuracy knob; 1 = full resolution).
        deferred: deferred back-propagation (False: direct, for comparison).
        chunk: similarity entries per block of the nearest-neighbour search.
        nn_precision: dtype of the nearest-neighbour search (``auto``: bf16 on CUDA, fp32 on CPU).
        checkpoint_every: iterations between checkpoints.
        seed: view order.
    """

    mode: str = "ist"
    iters: int = 600
    lr: float = 0.02
    style_weight: float = 1.0
    content_weight: float = 0.05
    tv_weight: float = 0.02
    style_loss: str = "auto"
    sw_projections: int = 64
    color_transfer: str = "both"
    color_max_gain: float = 1.3
    sh_rest: str = "zero"
    free_opacity: bool = False
    label_mode: str = "majority"
    feature_scale: float = 1.0
    deferred: bool = True
    chunk: int = DEFAULT_CHUNK
    nn_precision: str = "auto"
    checkpoint_every: int = 100
    seed: int = 0

    def validate(self) -> "Stage2Config":
        if self.mode not in MODES:
            raise InputError(f"--mode {self.mode}: use one of {', '.join(MODES)}")
        if self.iters < 0:
            raise InputError(f"--iters {self.iters}: must be >= 0")
        for k in ("lr", "style_weight", "content_weight", "tv_weight"):
            v = getattr(self, k)
            if not math.isfinite(v) or v < 0:
                raise InputError(f"--{k.replace('_', '-')} {v}: must be a finite number >= 0")
        if not 0 < self.feature_scale <= 4:
            raise InputError(f"--feature-scale {self.feature_scale}: must be in (0, 4]")
        if self.style_loss not in STYLE_LOSSES:
            raise InputError(f"--style-loss {self.style_loss}: use one of {', '.join(STYLE_LOSSES)}")
        if self.sw_projections < 1:
            raise InputError(f"--sw-projections {self.sw_projections}: must be >= 1")
        if self.color_transfer not in COLOR_TRANSFER:
            raise InputError(f"--color-transfer {self.color_transfer}: use one of {', '.join(COLOR_TRANSFER)}")
        if not (math.isfinite(self.color_max_gain) and self.color_max_gain > 0):
            raise InputError(f"--color-max-gain {self.color_max_gain}: must be a finite number > 0")
        if self.sh_rest not in SH_REST:
            raise InputError(f"--sh-rest {self.sh_rest}: use one of {', '.join(SH_REST)}")
        if self.label_mode not in ("majority", "nearest"):
            raise InputError(f"--label-mode {self.label_mode}: use majority or nearest")
        if self.nn_precision not in ("auto", "fp32", "bf16", "fp16"):
            raise InputError(f"--nn-precision {self.nn_precision}: use auto, fp32, bf16 or fp16")
        if self.chunk < 1:
            raise InputError(f"--chunk {self.chunk}: must be >= 1")
        if self.checkpoint_every < 1:
            raise InputError("--checkpoint-every must be >= 1")
        return self


# ----------------------------------------------------------------------------- rendering helpers
def render_rgb(scene: GaussianScene, cams: Cameras, background: Optional[torch.Tensor] = None,
               **kwargs) -> torch.Tensor:
    """``[C, H, W, 3]`` colour renders (background ``[3]`` blended behind)."""
    bg = None
    if background is not None:
        bg = background.to(scene.device, scene.dtype).reshape(1, 3).expand(len(cams), 3)
    colors, _, _ = scene.render(cams.to(scene.device), backgrounds=bg, **kwargs)
    return colors[..., :3]


def render_batched(scene: GaussianScene, cams: Cameras, background: Optional[torch.Tensor] = None,
                   batch: int = 1, desc: Optional[str] = None) -> torch.Tensor:
    """No-grad renders of many cameras, a few at a time (on the scene's device): ``[C,H,W,3]``."""
    from tqdm.auto import tqdm

    out = []
    with torch.no_grad():
        for s in tqdm(range(0, len(cams), batch), desc=desc, disable=desc is None, leave=False):
            out.append(render_rgb(scene, cams[list(range(s, min(s + batch, len(cams))))], background))
    return torch.cat(out, 0)


def render_alphas(scene: GaussianScene, cams: Cameras) -> torch.Tensor:
    """No-grad accumulated opacity ``[C, H, W]`` of many cameras, one at a time."""
    with torch.no_grad():
        return torch.cat([scene.render(cams[[c]].to(scene.device))[1][..., 0] for c in range(len(cams))])


def deferred_backward(render: Callable[[Cameras], torch.Tensor], camera: Cameras,
                      loss_fn: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Deferred back-propagation of ``loss_fn(render(camera))`` into the scene parameters.

    The image is rendered without gradient, ``dL/dimage`` is computed with the
    image as a leaf (the feature network's graph is freed right after), then
    the image is rendered again with gradient and ``dL/dimage`` is pushed
    through the rasterizer alone.

    Args:
        render: cameras -> ``[1, h, w, 3]`` (differentiable in the parameters).
        camera: one camera.
        loss_fn: image ``[H, W, 3]`` -> scalar.
    Returns: the loss (detached). Gradients are accumulated into the parameters' ``.grad``.
    """
    with torch.no_grad():
        image = render(camera)[0]
    image = image.detach().requires_grad_(True)
    loss = loss_fn(image)
    (grad,) = torch.autograd.grad(loss, image)
    del image
    render(camera)[0].backward(grad)
    return loss.detach()


def direct_backward(render: Callable[[Cameras], torch.Tensor], camera: Cameras,
                    loss_fn: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """Plain back-propagation of ``loss_fn(render(camera))`` (reference for :func:`deferred_backward`)."""
    loss = loss_fn(render(camera)[0])
    loss.backward()
    return loss.detach()


# ----------------------------------------------------------------------------- losses
def to_nchw(image: torch.Tensor) -> torch.Tensor:
    """``[H,W,3]`` or ``[B,H,W,3]`` -> ``[B,3,H,W]``."""
    return image.permute(2, 0, 1)[None] if image.ndim == 3 else image.permute(0, 3, 1, 2)


def extract(extractor, images: torch.Tensor, feature_scale: float = 1.0) -> torch.Tensor:
    """Stacked features ``[B, C, h, w]`` of images ``[B,H,W,3]`` / ``[H,W,3]`` (see :func:`stack_features`)."""
    from .features import stack_features

    x = to_nchw(images)
    if feature_scale != 1.0:
        size = (max(4, round(x.shape[-2] * feature_scale)), max(4, round(x.shape[-1] * feature_scale)))
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=feature_scale < 1)
    return stack_features(extractor(x))


def tv_loss(image: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of vertically and horizontally neighbouring pixels of ``[H,W,C]``."""
    return ((image[1:] - image[:-1]) ** 2).mean() + ((image[:, 1:] - image[:, :-1]) ** 2).mean()


def content_loss(feats: torch.Tensor, feats0: torch.Tensor) -> torch.Tensor:
    """Relative feature MSE ``mean((f - f0)^2) / mean(f0^2)``."""
    return ((feats - feats0) ** 2).mean() / (feats0 ** 2).mean().clamp_min(1e-12)


def style_loss_kind(cfg: Stage2Config, extractor) -> str:
    """The style loss ``cfg`` asks for with this extractor (``auto``: NNFM on VGG16 features, else SW)."""
    if cfg.style_loss != "auto":
        return cfg.style_loss
    return "nnfm" if str(getattr(extractor, "name", "")).startswith("vgg16") else "sw"


def build_targets(extractor, images: torch.Tensor, labels: Optional[torch.Tensor], cfg: Stage2Config,
                  size: Optional[tuple[int, int]] = None):
    """Style targets from style images ``[V,H,W,3]`` (key views or the style image) and their
    group maps ``[V,H,W]`` (None = global): a :class:`~ssgwarp.matching.MatchTargets` (NNFM) or a
    :class:`~ssgwarp.matching.SlicedTargets` (SW), see :func:`style_loss_kind`. ``size`` resizes
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
        extractor: a :class:`~ssgwarp.features.FeatureExtractor`.
        targets: the style features to match.
        cfg: weights and knobs.
        view_labels: ``[C, H, W]`` group maps of the training views (None: global).
        originals: ``[C, H, W, 3]`` renders of the unstylized scene (content target).
    """

    def __init__(self, extractor, targets: MatchTargets, cfg: Stage2Config,
                 view_labels: Optional[torch.Tensor] = None, originals: Optional[torch.Tensor] = None) -> None:
        self.extractor, self.targets, self.cfg = extractor, targets, cfg
        self.view_labels, self.originals = view_labels, originals
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
            content = content_loss(feats, f0)
            total = total + cfg.content_weight * content
            parts["content"] = float(content.detach())
        if cfg.tv_weight > 0:
            tv = tv_loss(image)
            total = total + cfg.tv_weight * tv
            parts["tv"] = float(tv.detach())
        parts["total"] = float(total.detach())
        self.last = parts
        return total


def finetune_loss(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``0.8 L1 + 0.2 (1 - SSIM)`` between ``[H,W,3]`` images (the 3DGS photometric loss)."""
    from .losses import photometric

    return photometric(image[None], target[None])


# ----------------------------------------------------------------------------- colour transfer
@torch.no_grad()
def transfer_colors(scene: GaussianScene, cameras: Cameras, target: torch.Tensor, *,
                    labels: Optional[torch.Tensor] = None,
                    target_labels: Optional[torch.Tensor] = None, assign: Optional[torch.Tensor] = None,
                    num_groups: Optional[int] = None, min_pixels: int = 64, max_gain: float = 1.3
                    ) -> tuple[GaussianScene, dict]:
    """ARF's colour transfer of ``scene``: its renders from ``cameras`` get the colour mean and
    covariance of ``target [V, H, W, 3]`` (the style image or the stylized key views), by one linear
    map of the SH coefficients (:mod:`ssgwarp.color`; view-consistent by construction).

    Per group when ``labels [C, H, W]`` (group maps of the renders), ``target_labels [V, H, W]``,
    ``assign [N]`` (each Gaussian's group) and ``num_groups`` are given: group ``g``'s Gaussians get
    the map from group ``g``'s rendered pixels to group ``g``'s target pixels, or — when ``g`` has
    fewer than ``min_pixels`` pixels on either side (absent from the key views) — the global map
    (all rendered pixels -> all target pixels). The source colours are the renders' surface colours
    (rendered without background and divided by alpha, so that the map is exact on them); pixels with
    alpha < 0.5 (background) are left out. Returns the recoloured scene and a record of what was done.
    """
    from .color import fit_group_transforms, fit_transform, pixel_stats, transform_sh

    renders, alphas = [], []
    for c in range(len(cameras)):   # rendered without background, un-premultiplied: the surface colour
        col, alpha, _ = scene.render(cameras[[c]].to(scene.device))
        renders.append(col[..., :3] / alpha.clamp_min(1e-6))
        alphas.append(alpha[..., 0])
    renders, alphas = torch.cat(renders), torch.cat(alphas)
    grouped = labels is not None and target_labels is not None and assign is not None and num_groups
    src = pixel_stats(renders, alphas, labels if grouped else None)
    tgt = pixel_stats(target.to(scene.device), None, target_labels if grouped else None)
    if grouped:
        transforms, how = fit_group_transforms(src, tgt, int(num_groups), min_pixels, max_gain=max_gain)
        out = transform_sh(scene, transforms, assign)
        info = {"per_group": True, "groups_matched": how.count("group"), "groups_global": how.count("global"),
                "how": how}
    else:
        t = fit_transform(src[0], tgt[0], max_gain=max_gain)
        out = transform_sh(scene, [t])
        info = {"per_group": False, "transform": t.to_list()}
    return out, info


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


def view_order(step: int, num_views: int, seed: int) -> int:
    """The training view of ``step``: a fresh seeded permutation every epoch (stateless, so resumable)."""
    epoch, k = divmod(step, num_views)
    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return int(torch.randperm(num_views, generator=g)[k])


# ----------------------------------------------------------------------------- the optimisation
@dataclass
class Stage2Result:
    scene: GaussianScene
    history: list[dict] = field(default_factory=list)
    last: dict = field(default_factory=dict)
    seconds: float = 0.0
    iters_done: int = 0


def optimise(scene: GaussianScene, cameras: Cameras, cfg: Stage2Config, *,
             loss: Optional[ViewLoss] = None,
             finetune_images: Optional[torch.Tensor] = None, finetune_cameras: Optional[Cameras] = None,
             background: Optional[torch.Tensor] = None, checkpoint: Optional[Path] = None,
             resume: bool = False, progress: bool = True, log_every: int = 10,
             render_kwargs: Optional[dict] = None) -> Stage2Result:
    """Run Stage 2 and return the stylized scene.

    Args:
        scene: the reconstructed (grouped) scene; its tensors are not modified.
        cameras: the training cameras (``ist`` / ``global``).
        cfg: options.
        loss: the per-view loss (``ist`` / ``global``).
        finetune_images, finetune_cameras: ``[V,H,W,3]`` stylized key views and their
            cameras (``finetune`` mode).
        background: ``[3]`` background colour.
        checkpoint: file to checkpoint into every ``cfg.checkpoint_every`` steps
            and on Ctrl-C; with ``resume`` the run continues from it.
    """
    from tqdm.auto import tqdm

    from .fileio import atomic_path

    cfg.validate()
    finetune = cfg.mode == "finetune"
    if finetune and (finetune_images is None or finetune_cameras is None):
        raise InputError("finetune mode needs the stylized key views (Stage 1 output)")
    if not finetune and loss is None:
        raise InputError(f"{cfg.mode} mode needs a ViewLoss")
    names = trainable_names(cfg, scene)
    if cfg.sh_rest == "zero" and scene.sh_rest is not None:
        scene = scene.replace(sh_rest=torch.zeros_like(scene.sh_rest))
    params = {n: getattr(scene, n).detach().clone().requires_grad_(True) for n in names}
    opt = torch.optim.Adam([{"params": [p], "lr": _lr(n, cfg), "name": n} for n, p in params.items()], eps=1e-15)
    start, history, elapsed = 0, [], 0.0
    if resume and checkpoint is not None and Path(checkpoint).is_file():
        state = torch.load(checkpoint, map_location=scene.device, weights_only=False)
        if state.get("params_names") != names or state.get("n") != len(scene) or state.get("mode") != cfg.mode:
            raise InputError(f"{checkpoint}: checkpoint is from a different run (mode, scene or options); "
                             f"use --force to start over")
        with torch.no_grad():
            for n in names:
                params[n].copy_(state["params"][n])
        opt.load_state_dict(state["optimizer"])
        start, history, elapsed = int(state["step"]), list(state["history"]), float(state["seconds"])

    def current() -> GaussianScene:
        return scene.replace(**params)

    rk = dict(render_kwargs or {})

    def render(cam: Cameras) -> torch.Tensor:
        return render_rgb(current(), cam, background, **rk)

    def save(step: int) -> None:
        if checkpoint is None:
            return
        state = {"step": step, "params": {n: p.detach() for n, p in params.items()}, "params_names": names,
                 "optimizer": opt.state_dict(), "history": history, "seconds": elapsed + time.perf_counter() - t0,
                 "n": len(scene), "mode": cfg.mode, "config": asdict(cfg)}
        with atomic_path(checkpoint) as tmp:
            torch.save(state, tmp)

    n_views = len(finetune_cameras) if finetune else len(cameras)
    if n_views == 0:
        raise InputError("Stage 2: no views to optimise on")
    t0 = time.perf_counter()
    done, last = start, (history[-1] if history else {})
    bar = tqdm(total=cfg.iters, initial=start, desc=f"stage 2 ({cfg.mode})", disable=not progress, leave=False)
    try:
        for step in range(start, cfg.iters):
            v = view_order(step, n_views, cfg.seed)
            opt.zero_grad(set_to_none=True)
            if finetune:
                target = finetune_images[v].to(scene.device, scene.dtype)
                value = direct_backward(render, finetune_cameras[v], lambda img: finetune_loss(img, target))
                parts = {"total": float(value)}
            else:
                cam = cameras[v]
                fn = lambda img: loss(img, v, step)  # noqa: E731
                if cfg.deferred:
                    value = deferred_backward(render, cam, fn)
                else:
                    value = direct_backward(render, cam, fn)
                parts = dict(loss.last)
            if not math.isfinite(float(value)):
                raise SsgwarpError(f"Stage 2: loss became {float(value)} at step {step}; last good checkpoint "
                                   f"kept (lower --lr and rerun with --resume)")
            opt.step()
            done = step + 1
            last = {"step": step, "view": v, **parts}
            if step % log_every == 0:
                history.append(last)
            bar.update(1)
            bar.set_postfix({k: f"{val:.4f}" for k, val in parts.items() if k in ("style", "total")})
            if done % cfg.checkpoint_every == 0 and done < cfg.iters:
                save(done)
    except KeyboardInterrupt:
        save(done)  # the steps applied completely; resume continues after them
        raise
    finally:
        bar.close()
    seconds = elapsed + time.perf_counter() - t0
    out = scene.replace(**{n: p.detach().clone() for n, p in params.items()})
    if checkpoint is not None:
        save(cfg.iters)
    return Stage2Result(out, history, last, seconds, cfg.iters)


# ----------------------------------------------------------------------------- end to end
@dataclass
class StylizeOptions:
    """Options of :func:`stylize_run` besides Stage 1 and Stage 2 (CLI flags of the same names).

    keyviews / ids / max_side: key-view choice and diffusion resolution (:mod:`ssgwarp.keyviews`);
    extractor / vgg16 / layers: the feature extractor (:func:`ssgwarp.features.load_extractor`);
    path_frames: frames of the smooth camera path (0: none); sheet_views: rows of the contact sheet;
    weights: the config file's ``weights`` mapping.
    """

    keyviews: int = 4
    ids: Optional[list[int]] = None
    max_side: int = 512
    extractor: str = "auto"
    vgg16: Optional[str] = None
    layers: Optional[list[str]] = None
    path_frames: int = 60
    sheet_views: int = 3
    weights: Optional[dict] = None


OUTPUTS = ("run.json", "keyviews", "stage2.ckpt", "scene.ply", "renders", "contact_sheet.png", "loss.png",
           "metrics.json")


def _say(msg: str, progress: bool) -> None:
    if progress:
        print(f"ssgwarp stylize: {msg}", flush=True)


def _signature(style: Path, scene_dir: Path, s2: Stage2Config, opts: StylizeOptions, s1) -> dict:
    """What must not change between a run and its ``--resume``."""
    cfg = {k: v for k, v in asdict(s2).items() if k not in ("iters", "checkpoint_every")}
    s1d = None
    if s1 is not None:
        s1d = {k: v for k, v in asdict(s1).items() if k not in ("progress", "weights")}
    sig = {"scene_dir": str(scene_dir.resolve()), "style": str(style.resolve()), "stage2": cfg,
           "keyviews": opts.keyviews, "ids": opts.ids, "max_side": opts.max_side, "extractor": opts.extractor,
           "vgg16": opts.vgg16, "layers": opts.layers, "stage1": s1d}
    return json.loads(json.dumps(sig, default=str))   # as it reads back from run.json (tuples -> lists)


def _prepare_out(out: Path, scene_dir: Path, signature: dict, resume: bool, force: bool) -> dict:
    from .fileio import read_json

    if out.resolve() == scene_dir.resolve():
        raise InputError(f"--out {out}: must differ from the scene folder (it would overwrite its scene.ply)")
    state: dict = {"signature": signature, "stages": {}}
    existing = [p for p in OUTPUTS if (out / p).exists()]
    if existing and resume:
        if (out / "run.json").is_file():
            old = read_json(out / "run.json")
            if old.get("signature") != signature:
                changed = sorted(k for k in signature if old.get("signature", {}).get(k) != signature[k])
                raise InputError(f"{out}: --resume with different options ({', '.join(changed)}); "
                                 f"use the same options or --force to start over")
            state["stages"] = dict(old.get("stages", {}))
    elif existing and not force:
        raise InputError(f"{out}: already holds a stylize output ({', '.join(existing)}); "
                         f"pass --resume to continue it or --force to overwrite it")
    elif existing and force:
        for p in existing:
            q = out / p
            shutil.rmtree(q) if q.is_dir() else q.unlink()
    out.mkdir(parents=True, exist_ok=True)
    return state


def fit_style(style: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``style [Hs,Ws,3]`` resized so its shorter side is ``min(height, width)`` (aspect kept): ``[1,h,w,3]``.

    (The rule :func:`ssgwarp.metrics.fit_style` uses for the Gram loss.)
    """
    x = style.permute(2, 0, 1)[None]
    k = min(height, width) / min(x.shape[-2:])
    size = (max(8, round(x.shape[-2] * k)), max(8, round(x.shape[-1] * k)))
    if size != tuple(x.shape[-2:]):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=k < 1.0)
    return x.permute(0, 2, 3, 1)


def _transfer_text(info: dict, against: str) -> str:
    if info.get("per_group"):
        return (f"per group against {against}: {info['groups_matched']} groups matched on their own, "
                f"{info['groups_global']} by the global map (absent from the key views)")
    return f"one global linear map against {against}"


def _group_maps(scene: GaussianScene, cams: Cameras, classifier, progress: bool) -> torch.Tensor:
    from .grouping import render_group_maps

    labels = []
    for c in range(len(cams)):  # one view at a time: the probabilities are dropped right away
        lab, _ = render_group_maps(scene, cams[c], classifier)
        labels.append(lab)
    return torch.cat(labels)


def _plot_losses(path: Path, history: list[dict], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .fileio import atomic_path

    if not history:
        return
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    steps = [h["step"] for h in history]
    for key in ("total", "style", "content", "tv"):
        if key in history[0]:
            ax.plot(steps, [h.get(key, float("nan")) for h in history], label=key)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def contact_sheet(path: Path, originals: torch.Tensor, stylized: torch.Tensor, style: torch.Tensor,
                  names: Sequence[str], title: str = "") -> Path:
    """A PNG with one row per view: original | stylized | style (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .fileio import atomic_path

    n = len(originals)
    h, w = originals.shape[1:3]
    fig, axes = plt.subplots(n, 3, figsize=(3 * 3.2, n * 3.2 * h / w + 0.6), dpi=110, squeeze=False)
    for i in range(n):
        for j, (img, label) in enumerate([(originals[i], f"original {names[i]}"), (stylized[i], "stylized"),
                                          (style, "style")]):
            ax = axes[i, j]
            ax.imshow(img.detach().float().clamp(0, 1).cpu().numpy())
            ax.set_title(label, fontsize=8)
            ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def _check_explicit_stage1_paths(stage1) -> None:
    """A Stage 1 weight path the user gave explicitly must exist (absent defaults just skip Stage 1)."""
    from . import weights as W
    from .diffusion import WEIGHT_KEYS

    for key in WEIGHT_KEYS:
        explicit = getattr(stage1, key, None)
        if explicit and W.find(key, explicit) is None:
            raise WeightsNotFound(W.message(key, explicit))


def stylize_run(scene_dir: str | Path, style_path: str | Path, out: str | Path, *,
                stage2: Optional[Stage2Config] = None, stage1=None, opts: Optional[StylizeOptions] = None,
                device: torch.device | str = "cpu", resume: bool = False, force: bool = False,
                progress: bool = True, stage1_models=None) -> dict:
    """``ssgwarp stylize``: key views, Stage 1 and Stage 2 on a (grouped) run; returns the metrics dict.

    Writes into ``out``: ``keyviews/`` (key views, stylized key views, sheet),
    ``stage2.ckpt``, ``scene.ply`` (the stylized scene), ``renders/train/*.png``
    and ``renders/path/frame_*.png``, ``contact_sheet.png``, ``loss.png``,
    ``metrics.json`` and ``run.json`` (options and finished stages, for ``resume``).
    ``stage1`` is a :class:`ssgwarp.diffusion.Stage1Config` (default: its
    defaults); ``stage1_models`` preloaded Stage 1 models (tests).
    """
    from tqdm.auto import tqdm

    from .datasets import load_run
    from .features import load_extractor
    from .fileio import read_image, write_image, write_json
    from .ply import write_ply

    t_start = time.perf_counter()
    stage2 = (stage2 or Stage2Config()).validate()
    opts = opts or StylizeOptions()
    if stage1 is None and stage2.mode != "global":
        from .diffusion import Stage1Config
        stage1 = Stage1Config(weights=opts.weights)
    scene_dir, style_path, out = Path(scene_dir), Path(style_path), Path(out)
    if opts.path_frames < 0 or opts.sheet_views < 1:
        raise InputError("--path-frames must be >= 0 and the contact sheet needs >= 1 view")
    device = torch.device(device)
    style_np = read_image(style_path, 3)                       # InputError when missing / corrupt
    scene, data = load_run(scene_dir, device, load_images=False)
    # weights first: a missing or corrupt file must fail before anything is written to OUT
    extractor = load_extractor(opts.vgg16, device, opts.layers, kind=opts.extractor, seed=stage2.seed,
                               config=opts.weights)
    if stage1 is not None and stage2.mode != "global" and stage1_models is None:
        _check_explicit_stage1_paths(stage1)
    state = _prepare_out(out, scene_dir, _signature(style_path, scene_dir, stage2, opts,
                                                    stage1 if stage2.mode != "global" else None), resume, force)
    times: dict[str, float] = {}

    def mark(stage: str, **info) -> None:
        state["stages"][stage] = {"done": True, **info}
        write_json(out / "run.json", state)

    write_json(out / "run.json", state)
    cams = data.cameras.to(device)
    train_ids = list(data.train_ids) or list(range(len(cams)))
    train_cams = cams[train_ids]
    bg = torch.tensor(data.background[:3], dtype=scene.dtype, device=device)
    style = torch.from_numpy(style_np).to(device)

    classifier, num_groups = None, None
    if (scene_dir / "groups").is_dir():
        if scene.identities is None:
            _say(f"{scene_dir}/groups exists but scene.ply has no identity fields: using one group", progress)
        else:
            from .grouping import load_groups
            gm = load_groups(scene_dir, device)
            classifier, num_groups = gm.classifier, gm.num_groups

    _say(f"{len(scene)} Gaussians, {len(train_ids)} training views {cams.width}x{cams.height}, "
         f"{'%d groups' % num_groups if num_groups else 'no groups (one group)'}, features {extractor.name}, "
         f"device {device}", progress)

    # -- key views and Stage 1 ---------------------------------------------------------------------
    kv, stylized, stage1_info = None, None, {"ran": False}
    if stage2.mode == "global":
        stage1_info["reason"] = "global mode matches against the style image (no key views)"
    else:
        from . import keyviews as K

        kv_dir = out / "keyviews"
        t0 = time.perf_counter()
        if resume and (kv_dir / "keyviews.json").is_file() and state["stages"].get("keyviews", {}).get("done"):
            kv, stylized = K.load_keyviews(kv_dir, device)
            times["keyviews"] = state["stages"]["keyviews"].get("seconds", 0.0)
            _say(f"key views {kv.ids} loaded from {kv_dir}", progress)
        else:
            ids = K.select_keyviews(cams, opts.keyviews, opts.ids, candidates=train_ids)
            size = K.diffusion_size(cams.width, cams.height, opts.max_side)
            kv = K.render_keyviews(scene, cams, ids, size, classifier, background=data.background)
            K.save_keyviews(kv, kv_dir)
            times["keyviews"] = time.perf_counter() - t0
            mark("keyviews", seconds=times["keyviews"], ids=list(kv.ids))
            _say(f"key views {kv.ids} ({', '.join(kv.cameras.names)}) at {size[0]}x{size[1]} -> {kv_dir}", progress)

        t0 = time.perf_counter()
        if stylized is not None:
            times["stage1"] = state["stages"].get("stage1", {}).get("seconds", 0.0)
            stage1_info = {"ran": True, "cvsa": bool(stage1.cvsa), "resumed": True}
        else:
            from .diffusion import missing_weights, stylize_keyviews

            # check the weights before anything imports diffusers (seconds of import for nothing)
            missing = [] if stage1_models is not None else missing_weights(stage1)
            if missing:
                stylized = None
                _say("Stage 1 skipped (no local diffusion weights: " + " | ".join(missing) + ")", progress)
            else:
                _say(f"Stage 1: diffusion on {len(kv)} key views (CVSA {'on' if stage1.cvsa else 'off'})", progress)
                stylized = stylize_keyviews(kv, style_np, stage1, device, models=stage1_models)
                missing = [] if stylized is not None else missing_weights(stage1)
            times["stage1"] = time.perf_counter() - t0
            if stylized is None:
                stage1_info = {"ran": False, "reason": "no local diffusion weights: " + " | ".join(missing),
                               "cvsa": bool(stage1.cvsa)}
            else:
                stage1_info = {"ran": True, "cvsa": bool(stage1.cvsa), "steps": stage1.steps,
                               "guidance": stage1.guidance, "ip_adapter_scale": stage1.ip_adapter_scale}
                K.save_keyviews(kv, kv_dir, stylized.to(kv.rgb.device), extra={"stage1": stage1_info})
            mark("stage1", seconds=times["stage1"], **stage1_info)

    # -- Stage 2 -------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    originals = render_batched(scene, train_cams, bg, desc="original renders" if progress else None)
    use_keys = stylized is not None and stage2.mode in ("ist", "finetune")
    key_images = key_cams = key_labels = view_labels = assign = None
    if use_keys:
        from .keyviews import from_diffusion

        key_images = from_diffusion(stylized.to(device).float(), cams.width, cams.height).to(scene.dtype)
        key_cams = cams[list(kv.ids)]
        if classifier is not None:
            from .grouping import gaussian_groups

            key_labels = _group_maps(scene, key_cams, classifier, progress)
            assign = gaussian_groups(scene, classifier)[0]

    # colour transfer (ARF): against the stylized key views (per group when grouped) or the style image
    def color_transfer(sc: GaussianScene) -> tuple[GaussianScene, dict]:
        if use_keys:
            return transfer_colors(sc, key_cams, key_images, labels=key_labels, target_labels=key_labels,
                                   assign=assign, num_groups=num_groups, max_gain=stage2.color_max_gain)
        return transfer_colors(sc, train_cams, style[None].to(scene.dtype), max_gain=stage2.color_max_gain)

    transfer: dict = {"setting": stage2.color_transfer,
                      "against": "the stylized key views" if use_keys else "the style image"}
    work = scene
    if stage2.color_transfer in ("pre", "both"):
        work, transfer["pre"] = color_transfer(scene)
        _say("colour transfer (pre): " + _transfer_text(transfer["pre"], transfer["against"]), progress)
    content_ref = originals if work is scene else render_batched(work, train_cams, bg)
    loss, ft_images, ft_cams = None, None, None
    if use_keys:
        if stage2.mode == "finetune":
            matching = "none (fine-tuned on the stylized key views)"
            ft_images, ft_cams = key_images, key_cams
        else:
            if classifier is not None:
                view_labels = _group_maps(scene, train_cams, classifier, progress)
            targets = build_targets(extractor, key_images, key_labels, stage2)
            matching = (f"per group ({num_groups} groups) against {len(kv)} stylized key views"
                        if classifier is not None else f"global against {len(kv)} stylized key views (no groups)")
            loss = ViewLoss(extractor, targets, stage2, view_labels=view_labels, originals=content_ref)
    else:
        targets = build_targets(extractor, fit_style(style.to(scene.dtype), cams.height, cams.width), None, stage2)
        loss = ViewLoss(extractor, targets, stage2, originals=content_ref)
        matching = "global against the style image"
        if stage2.mode != "global":
            matching += f" (Stage 1 did not run: requested mode '{stage2.mode}' fell back)"
            _say("Stage 1 did not run: Stage 2 matches against the style image globally", progress)
    run_cfg = stage2
    if stage2.mode == "finetune" and ft_images is None:   # no stylized key views to fit: global fallback
        run_cfg = dataclasses.replace(stage2, mode="global")
    _say(f"Stage 2 ({stage2.mode}): {stage2.iters} steps, matching {matching}", progress)
    res = optimise(work, train_cams, run_cfg, loss=loss, finetune_images=ft_images, finetune_cameras=ft_cams,
                   background=bg, checkpoint=out / "stage2.ckpt", resume=resume, progress=progress)
    styled = res.scene
    if stage2.color_transfer in ("post", "both"):
        styled, transfer["post"] = color_transfer(styled)
        _say("colour transfer (post): " + _transfer_text(transfer["post"], transfer["against"]), progress)
    times["stage2"] = time.perf_counter() - t0
    times["stage2_optimisation"] = res.seconds
    write_ply(out / "scene.ply", styled)
    mark("stage2", seconds=times["stage2"], iters=stage2.iters)
    _plot_losses(out / "loss.png", res.history, f"Stage 2 ({stage2.mode}, {extractor.name})")

    # -- renders -------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    renders = render_batched(styled, train_cams, bg, desc="train renders" if progress else None)
    for i, img in enumerate(renders):
        write_image(out / "renders" / "train" / f"{Path(train_cams.names[i]).stem}.png", img.clamp(0, 1))
    if opts.path_frames > 0:
        from .render import smooth_path

        path = smooth_path(train_cams, opts.path_frames).to(device)
        for s in tqdm(range(len(path)), desc="path renders", disable=not progress, leave=False):
            with torch.no_grad():
                frame = render_rgb(styled, path[[s]], bg)[0]
            write_image(out / "renders" / "path" / f"frame_{s:04d}.png", frame.clamp(0, 1))
    times["renders"] = time.perf_counter() - t0

    # -- metrics and sheet ---------------------------------------------------------------------------
    from .metrics import StyleDistance, style_content_losses

    t0 = time.perf_counter()
    with torch.no_grad():
        after = style_content_losses(extractor, renders.float(), style.float(), originals.float())
        before = style_content_losses(extractor, originals.float(), style.float())
        dist = StyleDistance(style.float())          # on the scene's pixels (alpha >= 0.5), not the background
        alphas = render_alphas(scene, train_cams)
        alphas_after = render_alphas(styled, train_cams) if stage2.free_opacity else alphas
        dist_after, dist_before = dist.mean(renders.float(), alphas_after), dist.mean(originals.float(), alphas)
    times["metrics"] = time.perf_counter() - t0
    rows = sorted({round(i * (len(train_ids) - 1) / max(1, opts.sheet_views - 1))
                   for i in range(min(opts.sheet_views, len(train_ids)))})
    contact_sheet(out / "contact_sheet.png", originals[rows], renders[rows], style,
                  [Path(train_cams.names[r]).stem for r in rows],
                  title=f"{stage2.mode}: {matching}; features {extractor.name}")
    times["total"] = time.perf_counter() - t_start
    metrics = {
        "source_scene": str(scene_dir.resolve()),
        "style": str(style_path.resolve()),
        "mode": stage2.mode,
        "matching": matching,
        "stage1": stage1_info,
        "extractor": extractor.name,
        "style_loss": style_loss_kind(stage2, extractor),
        "gram_style_loss": float(after["style"].mean()),
        "gram_style_loss_original": float(before["style"].mean()),
        "style_distance": dist_after,
        "style_distance_original": dist_before,
        "metric_views": f"the {len(train_ids)} training views (ssgwarp evaluate scores novel path views)",
        "content_loss": float(after["content"].mean()),
        "color_transfer": transfer,
        "final_losses": res.last,
        "keyviews": None if kv is None else {"ids": list(kv.ids), "names": list(kv.cameras.names),
                                              "size": list(kv.size)},
        "groups": num_groups,
        "gaussians": len(styled),
        "views": len(train_ids),
        "resolution": [cams.width, cams.height],
        "optimised": trainable_names(stage2, scene),
        "config": asdict(stage2),
        "seconds": times,
        "device": str(device) if device.type != "cuda" else f"cuda ({torch.cuda.get_device_name(device)})",
        "outputs": {"scene": "scene.ply", "renders": "renders/train", "path": "renders/path",
                    "contact_sheet": "contact_sheet.png", "loss_plot": "loss.png", "keyviews": "keyviews"},
    }
    write_json(out / "metrics.json", metrics)
    mark("done", seconds=times["total"])
    d0, d1 = metrics["style_distance_original"], metrics["style_distance"]
    g = lambda x: "n/a" if x is None else f"{x:.3g}"  # noqa: E731
    _say(f"done in {times['total']:.1f}s: style distance colour {g(d0['color'])} -> {g(d1['color'])}, "
         f"texture {g(d0['texture'])} -> {g(d1['texture'])}; Gram style loss "
         f"{metrics['gram_style_loss_original']:.4g} -> {metrics['gram_style_loss']:.4g}, content "
         f"{metrics['content_loss']:.4g}; contact sheet {out / 'contact_sheet.png'}", progress)
    return metrics


# ----------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene_dir", type=Path, help="a reconstruction run (scene.ply, cameras.json, data.json; "
                                                "groups/ when grouped)")
    p.add_argument("--style", type=Path, required=True, help="style image (PNG/JPG)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or stage messages")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--mode", default="ist", choices=MODES,
                   help="ist: per-group matching to the stylized key views (default); finetune: fit the "
                        "stylized key views directly; global: ARF-style matching to the style image")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run in --out")
    p.add_argument("--force", action="store_true", help="overwrite an existing output in --out")
    g = p.add_argument_group("key views")
    g.add_argument("--keyviews", type=int, default=4, metavar="K", help="number of key views (default 4)")
    g.add_argument("--ids", default=None, help="comma-separated camera indices of the key views (default: chosen)")
    g.add_argument("--max-side", type=int, default=512, help="key-view (diffusion) longer side (default 512)")
    from .diffusion import add_stage1_arguments

    add_stage1_arguments(p)
    d = Stage2Config()
    g = p.add_argument_group("Stage 2 (instance-level style transfer)")
    g.add_argument("--iters", type=int, default=d.iters, help=f"optimisation steps (default {d.iters})")
    g.add_argument("--lr", type=float, default=d.lr, help=f"learning rate of the SH DC colour (default {d.lr})")
    g.add_argument("--style-weight", type=float, default=d.style_weight, help="NNFM style loss weight")
    g.add_argument("--content-weight", type=float, default=d.content_weight,
                   help=f"content loss weight (relative feature MSE; default {d.content_weight})")
    g.add_argument("--tv-weight", type=float, default=d.tv_weight, help=f"total variation weight (default {d.tv_weight})")
    g.add_argument("--style-loss", default=d.style_loss, choices=STYLE_LOSSES,
                   help="nnfm: nearest-neighbour feature matching (the paper's); sw: sliced Wasserstein "
                        "between feature distributions; auto (default): NNFM on VGG16 features, SW on the "
                        "weight-free random features")
    g.add_argument("--sw-projections", type=int, default=d.sw_projections,
                   help=f"random directions per step of the sw loss (default {d.sw_projections})")
    g.add_argument("--color-transfer", default=d.color_transfer, choices=COLOR_TRANSFER,
                   help="ARF's view-consistent colour transfer (colour mean and covariance matched to the "
                        "stylized key views, per group, or to the style image) before the optimisation, "
                        f"after it, both or off (default {d.color_transfer})")
    g.add_argument("--color-max-gain", type=float, default=d.color_max_gain,
                   help="largest factor by which the colour transfer may stretch colour differences "
                        f"(default {d.color_max_gain}; higher: closer colours, lower: smaller consistency error)")
    g.add_argument("--sh-rest", default=d.sh_rest, choices=SH_REST,
                   help=f"higher SH bands (view-dependent colour): keep, zero at the start, or optimise "
                        f"(default {d.sh_rest})")
    g.add_argument("--sh-bands", action="store_true", help="same as --sh-rest optimise")
    g.add_argument("--free-opacity", action="store_true", help="also optimise opacities")
    g.add_argument("--label-mode", default=d.label_mode, choices=("majority", "nearest"),
                   help="group maps to feature resolution (default majority)")
    g.add_argument("--feature-scale", type=float, default=d.feature_scale,
                   help="resize images by this factor before the feature extractor (default 1)")
    g.add_argument("--direct", action="store_true", help="direct back-propagation instead of deferred")
    g.add_argument("--chunk", type=int, default=d.chunk, help="similarity entries per nearest-neighbour block")
    g.add_argument("--nn-precision", default=d.nn_precision, choices=("auto", "fp32", "bf16", "fp16"),
                   help="nearest-neighbour search precision (auto: bf16 on CUDA, fp32 on CPU)")
    g.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every, help="steps between checkpoints")
    g.add_argument("--extractor", default="auto", choices=("auto", "vgg16", "random"),
                   help="features: auto = VGG16 when local weights exist, else seeded random multi-scale")
    g.add_argument("--vgg16", default=None, help="torchvision VGG16 state dict (or SSGWARP_VGG16)")
    g.add_argument("--layers", default=None, help="VGG16 layers, comma separated (default conv3 = relu3_1..3)")
    g = p.add_argument_group("outputs")
    g.add_argument("--path-frames", type=int, default=60, help="frames along a smooth camera path (0: none)")
    g.add_argument("--sheet-views", type=int, default=3, help="views in the contact sheet")


def run(args) -> int:
    from .diffusion import config_from_args
    from .keyviews import parse_ids

    weights = getattr(args, "weights", None)
    weights = weights if isinstance(weights, dict) else None
    s2 = Stage2Config(mode=args.mode, iters=args.iters, lr=args.lr, style_weight=args.style_weight,
                      content_weight=args.content_weight, tv_weight=args.tv_weight,
                      style_loss=args.style_loss, sw_projections=args.sw_projections,
                      color_transfer=args.color_transfer, color_max_gain=args.color_max_gain,
                      sh_rest="optimise" if args.sh_bands else args.sh_rest,
                      free_opacity=args.free_opacity, label_mode=args.label_mode,
                      feature_scale=args.feature_scale, deferred=not args.direct, chunk=args.chunk,
                      nn_precision=args.nn_precision,
                      checkpoint_every=args.checkpoint_every, seed=args.seed)
    opts = StylizeOptions(keyviews=args.keyviews, ids=parse_ids(args.ids), max_side=args.max_side,
                          extractor=args.extractor, vgg16=args.vgg16,
                          layers=[s.strip() for s in args.layers.split(",")] if args.layers else None,
                          path_frames=args.path_frames, sheet_views=args.sheet_views, weights=weights)
    s1 = config_from_args(args) if args.mode != "global" else None
    stylize_run(args.scene_dir, args.style, args.out, stage2=s2, stage1=s1, opts=opts, device=args.device,
                resume=args.resume, force=args.force, progress=not args.quiet)
    return 0
