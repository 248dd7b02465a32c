"""Stage 1: stylize the key views with SD1.5 + depth ControlNet + IP-Adapter, DDIM inversion and CVSA.

For K key views ``rgb [K,H,W,3]`` with depth ``[K,H,W]`` (H, W multiples of 8):

1. encode each view with the VAE (posterior mean x ``scaling_factor``);
2. DDIM-invert the latents under the depth ControlNet (disparity ``1/depth``
   normalised to [0, 1] per view, 0 where nothing was rendered), with guidance 0:
   only the unconditional branch (negative prompt, zero image embedding) and
   no CVSA, one view independent of the others;
3. DDIM-denoise all K views together with classifier-free guidance: the style
   prompt and the style image through IP-Adapter (scale and per-block scales
   configurable) on the conditional half, CVSA on the self-attention layers of
   the chosen blocks (:mod:`ssgwarp.stylization.cvsa`), ControlNet on both halves; ``eta``
   > 0 adds seeded DDIM noise;
4. decode to images in [0, 1].

``strength`` < 1 inverts/denoises only the last ``round(strength * steps)``
steps of the schedule (closer to the original views). Inversion and denoising
use the same timesteps and the same cumulative alphas, so with guidance 0 and
no CVSA, denoising undoes the inversion up to the DDIM discretisation error
(measured in tests/test_diffusion.py and docs/stage1.md).

Weights (:mod:`ssgwarp.services.weights`): ``sd15`` (diffusers layout: unet/, vae/,
scheduler/, text_encoder/, tokenizer/; ``stable-diffusion-v1-5/stable-diffusion-v1-5``),
``controlnet_depth`` (diffusers ControlNet folder; ``lllyasviel/control_v11f1p_sd15_depth``),
``ip_adapter`` (``ip-adapter_sd15.safetensors`` or ``.bin``; ``h94/IP-Adapter``) and
``image_encoder`` (transformers CLIPVisionModelWithProjection folder;
``h94/IP-Adapter`` ``models/image_encoder``), from explicit paths, the config,
the environment, ``$SSGWARP_WEIGHTS`` or the Hugging Face cache, and downloaded
into that cache on first use unless downloads are off. Without them
:func:`stylize_keyviews` prints a notice and returns None: Stage 2 then matches
against the style image globally. Random-weight stand-ins for tests and
benchmarks live in ``tests/fakeweights.py``.

diffusers and transformers are imported inside functions (heavy imports).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Mapping, Optional

import numpy as np
import torch

from .cvsa import cvsa_enabled
from .diffusion_models import Stage1Config, Stage1Models, load_stage1, set_ip_adapter_scales
from ..errors import InputError, SsgwarpError, WeightsNotFound
from ..core.fileio import read_image

__all__ = ["depth_to_control", "schedule", "ddim_step", "encode_latents", "decode_latents", "predict_noise",
           "ddim_invert", "ddim_denoise", "stylize_views", "stylize_keyviews", "add_stage1_arguments",
           "config_from_args"]

# -- conditioning -------------------------------------------------------------------------------
def depth_to_control(depth: torch.Tensor, alpha: Optional[torch.Tensor] = None, min_alpha: float = 0.5
                     ) -> torch.Tensor:
    """Depth-ControlNet condition ``[K, 3, H, W]`` in [0, 1] from expected depth ``[K, H, W]``.

    Disparity ``1/depth`` is normalised per view to [0, 1] over valid pixels
    (depth > 0, finite, and alpha >= ``min_alpha`` when alpha is given): near is
    1 (white), far 0; invalid pixels are 0. A view whose valid disparities are
    all equal gets 1 on its valid pixels.
    """
    d = depth.float()
    valid = torch.isfinite(d) & (d > 0)
    if alpha is not None:
        valid &= alpha.float() >= min_alpha
    disp = torch.where(valid, 1.0 / d.clamp_min(1e-12), torch.zeros_like(d))
    out = torch.zeros_like(d)
    for i in range(d.shape[0]):
        v = valid[i]
        if not bool(v.any()):
            continue
        lo, hi = disp[i][v].min(), disp[i][v].max()
        span = hi - lo
        out[i] = torch.where(v, (disp[i] - lo) / span if float(span) > 1e-12 else torch.ones_like(disp[i]),
                             torch.zeros_like(disp[i]))
    return out[:, None].expand(-1, 3, -1, -1).contiguous()


# -- DDIM -----------------------------------------------------------------------------------------
def schedule(scheduler, steps: int, strength: float = 1.0) -> tuple[list[int], list[float], float]:
    """``(timesteps descending, their alphas_cumprod, final alpha)`` for ``steps`` DDIM steps.

    With ``strength`` < 1 only the last ``max(1, round(strength * steps))`` timesteps are kept.
    """
    scheduler.set_timesteps(int(steps))
    ts = [int(t) for t in scheduler.timesteps]
    n = max(1, min(len(ts), int(round(float(strength) * len(ts)))))
    ts = ts[len(ts) - n:]
    ac = scheduler.alphas_cumprod
    return ts, [float(ac[t]) for t in ts], float(scheduler.final_alpha_cumprod)


def ddim_step(x: torch.Tensor, eps: torch.Tensor, a_from: float, a_to: float, eta: float = 0.0,
              noise: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Move ``x`` from noise level ``a_from`` (alpha_cumprod) to ``a_to`` along predicted noise ``eps``.

    Deterministic DDIM (``eta = 0``) in either direction (inversion when
    ``a_to < a_from``); with ``eta > 0`` (denoising only) adds
    ``sigma * noise``, ``sigma = eta sqrt((1-a_to)/(1-a_from)) sqrt(1 - a_from/a_to)``.
    """
    x0 = (x - math.sqrt(1.0 - a_from) * eps) / math.sqrt(a_from)
    if eta > 0.0 and noise is not None and a_to > a_from:
        sigma = eta * math.sqrt((1.0 - a_to) / (1.0 - a_from)) * math.sqrt(max(0.0, 1.0 - a_from / a_to))
        dir_coef = math.sqrt(max(0.0, 1.0 - a_to - sigma ** 2))
        return math.sqrt(a_to) * x0 + dir_coef * eps + sigma * noise
    return math.sqrt(a_to) * x0 + math.sqrt(1.0 - a_to) * eps


@torch.no_grad()
def encode_latents(models: Stage1Models, rgb: torch.Tensor) -> torch.Tensor:
    """``rgb [K, H, W, 3]`` in [0, 1] → latents ``[K, 4, H/f, W/f]`` float32 (posterior mean x scaling)."""
    vae = models.vae
    sf = float(vae.config.scaling_factor)
    out = []
    for i in range(rgb.shape[0]):
        x = rgb[i:i + 1].permute(0, 3, 1, 2).to(models.device, models.dtype) * 2.0 - 1.0
        out.append(vae.encode(x).latent_dist.mean.float() * sf)
    return torch.cat(out)


@torch.no_grad()
def decode_latents(models: Stage1Models, latents: torch.Tensor) -> torch.Tensor:
    """latents ``[K, 4, h, w]`` → images ``[K, H, W, 3]`` float32 in [0, 1]."""
    vae = models.vae
    sf = float(vae.config.scaling_factor)
    out = []
    for i in range(latents.shape[0]):
        img = vae.decode((latents[i:i + 1] / sf).to(models.device, models.dtype)).sample.float()
        out.append(((img + 1.0) * 0.5).clamp(0, 1).permute(0, 2, 3, 1))
    img = torch.cat(out)
    if not torch.isfinite(img).all():
        raise SsgwarpError("Stage 1 produced non-finite pixels (half precision overflow?): retry with dtype fp32")
    return img


@torch.no_grad()
def predict_noise(models: Stage1Models, x: torch.Tensor, t: int, text: torch.Tensor,
                  image_embeds: Optional[torch.Tensor], control: torch.Tensor, controlnet_scale: float = 1.0
                  ) -> torch.Tensor:
    """Predicted noise ``[B, 4, h, w]`` (float32) of the UNet + ControlNet at timestep ``t``.

    ``text [B, L, D]``; ``image_embeds [B, E]`` (IP-Adapter) or None; ``control [B, 3, H, W]``.
    v-prediction models are converted to noise.
    """
    xin = x.to(models.device, models.dtype)
    text = text.to(models.device, models.dtype)
    down, mid = models.controlnet(xin, t, encoder_hidden_states=text,
                                  controlnet_cond=control.to(models.device, models.dtype),
                                  conditioning_scale=float(controlnet_scale), return_dict=False)
    added = None
    if models.has_ip_adapter:
        if image_embeds is None:
            raise ValueError("the UNet carries an IP-Adapter: image_embeds are required")
        added = {"image_embeds": [image_embeds.to(models.device, models.dtype)[:, None]]}
    out = models.unet(xin, t, encoder_hidden_states=text, added_cond_kwargs=added,
                      down_block_additional_residuals=down, mid_block_additional_residual=mid,
                      return_dict=False)[0].float()
    if models.scheduler.config.prediction_type == "v_prediction":
        a = float(models.scheduler.alphas_cumprod[int(t)])
        out = math.sqrt(a) * out + math.sqrt(1.0 - a) * x.float()
    return out


def _progress(it, desc: str, enabled: bool):
    from ..core.progress import tqdm

    return tqdm(it, desc=desc, leave=False, disable=not enabled, unit="step")


@torch.no_grad()
def ddim_invert(models: Stage1Models, latents: torch.Tensor, sched: tuple, text: torch.Tensor,
                image_embeds: Optional[torch.Tensor], control: torch.Tensor, controlnet_scale: float = 1.0,
                progress: bool = False) -> torch.Tensor:
    """DDIM inversion of clean ``latents [K, 4, h, w]`` to the first timestep of ``sched`` (guidance 0).

    ``sched`` is :func:`schedule`'s result; ``text``/``image_embeds``/``control``
    have batch K (the unconditional inputs in Stage 1). Each step moves from the
    previous level to timestep ``t`` with the noise predicted at ``t``.
    """
    ts, alphas, a_final = sched
    x = latents.float().to(models.device)
    n = len(ts)
    for i in _progress(range(n - 1, -1, -1), "DDIM inversion", progress):
        a_from = a_final if i == n - 1 else alphas[i + 1]
        eps = predict_noise(models, x, ts[i], text, image_embeds, control, controlnet_scale)
        x = ddim_step(x, eps, a_from, alphas[i])
    return x


@torch.no_grad()
def ddim_denoise(models: Stage1Models, latents: torch.Tensor, sched: tuple, text_uncond: torch.Tensor,
                 text_cond: torch.Tensor, image_uncond: Optional[torch.Tensor], image_cond: Optional[torch.Tensor],
                 control: torch.Tensor, guidance: float = 7.5, controlnet_scale: float = 1.0, eta: float = 0.0,
                 generator: Optional[torch.Generator] = None, cvsa: bool = False, cvsa_blocks=("last",),
                 cvsa_views_per_call: Optional[int] = None, progress: bool = False) -> torch.Tensor:
    """DDIM denoising of ``latents [K, 4, h, w]`` from the first timestep of ``sched`` to clean latents.

    Classifier-free guidance ``eps = eps_u + guidance (eps_c - eps_u)`` with the
    batch ``[uncond views; cond views]`` in one UNet call (only the half needed
    when guidance is 0 or 1). Conditioning tensors have batch K. With ``cvsa``
    the K views of each half share self-attention on ``cvsa_blocks``.
    ``eta > 0`` draws noise from ``generator`` (CPU) for reproducibility.
    """
    ts, alphas, a_final = sched
    K = latents.shape[0]
    w = float(guidance)
    halves = ["u"] if w == 0.0 else ["c"] if w == 1.0 else ["u", "c"]
    text = torch.cat([text_uncond if h == "u" else text_cond for h in halves])
    img = None
    if image_cond is not None:
        img = torch.cat([image_uncond if h == "u" else image_cond for h in halves])
    ctrl = torch.cat([control] * len(halves))
    x = latents.float().to(models.device)
    with cvsa_enabled(models.unet, K, cvsa_blocks, cvsa_views_per_call, enabled=cvsa):
        for i in _progress(range(len(ts)), "Stage 1 denoising", progress):
            eps_all = predict_noise(models, torch.cat([x] * len(halves)), ts[i], text, img, ctrl, controlnet_scale)
            if len(halves) == 2:
                eu, ec = eps_all.chunk(2)
                eps = eu + w * (ec - eu)
            else:
                eps = eps_all
            a_to = alphas[i + 1] if i + 1 < len(ts) else a_final
            noise = None
            if eta > 0.0:
                noise = torch.randn(x.shape, generator=generator, dtype=torch.float32).to(x.device)
            x = ddim_step(x, eps, alphas[i], a_to, eta, noise)
    return x


# -- Stage 1 ---------------------------------------------------------------------------------------
def _style_tensor(style) -> torch.Tensor:
    if isinstance(style, (str, Path)):
        style = read_image(style, 3)
    t = torch.as_tensor(np.asarray(style) if not isinstance(style, torch.Tensor) else style).float()
    if t.ndim != 3 or t.shape[-1] < 3:
        raise InputError(f"style image must be [H, W, 3], got shape {tuple(t.shape)}")
    return t[..., :3].cpu()


@torch.no_grad()
def stylize_views(models: Stage1Models, rgb: torch.Tensor, depth: torch.Tensor, style, cfg: Stage1Config,
                  alpha: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Stylize K views: ``rgb [K, H, W, 3]`` in [0, 1], ``depth [K, H, W]`` → ``[K, H, W, 3]`` float32 (CPU).

    H and W must be multiples of the VAE factor (8 for SD1.5). Steps in the module docstring.
    """
    cfg.validate()
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise InputError(f"key views must be [K, H, W, 3], got {tuple(rgb.shape)}")
    K, H, W, _ = rgb.shape
    f = models.vae_scale_factor
    if H % f or W % f:
        raise InputError(f"key views are {W}x{H}: width and height must be multiples of {f} "
                         "(render them at ssgwarp.stylization.keyviews.diffusion_size)")
    if depth.shape != (K, H, W):
        raise InputError(f"depth must be [K={K}, H={H}, W={W}], got {tuple(depth.shape)}")
    control = depth_to_control(depth.cpu(), None if alpha is None else alpha.cpu())
    text_u = models.encode_prompt([cfg.negative_prompt]).expand(K, -1, -1)
    text_c = models.encode_prompt([cfg.prompt]).expand(K, -1, -1)
    img_u = img_c = None
    if models.has_ip_adapter:
        set_ip_adapter_scales(models.unet, cfg.ip_adapter_scale, cfg.ip_adapter_block_scales)
        img_c = models.encode_style(_style_tensor(style)).expand(K, -1)
        img_u = torch.zeros_like(img_c)
    sched = schedule(models.scheduler, cfg.steps, cfg.strength)
    latents = encode_latents(models, rgb)
    xt = ddim_invert(models, latents, sched, text_u, img_u, control, cfg.controlnet_scale, cfg.progress)
    gen = torch.Generator("cpu").manual_seed(int(cfg.seed))
    x0 = ddim_denoise(models, xt, sched, text_u, text_c, img_u, img_c, control, cfg.guidance,
                      cfg.controlnet_scale, cfg.eta, gen, cfg.cvsa, tuple(cfg.cvsa_blocks),
                      cfg.cvsa_views_per_call, cfg.progress)
    return decode_latents(models, x0).cpu()


def stylize_keyviews(keyviews, style_image, cfg: Stage1Config, device, models: Optional[Stage1Models] = None
                     ) -> Optional[torch.Tensor]:
    """Stage 1 on :class:`ssgwarp.stylization.keyviews.KeyViews`: stylized views ``[K, H, W, 3]``, or None without weights.

    When the weights are absent it prints a notice (Stage 1 skipped; Stage 2
    matches against the style image globally) and returns None.
    """
    if models is None:
        try:
            models = load_stage1(cfg, device)
        except WeightsNotFound as e:
            print(f"ssgwarp: Stage 1 skipped: {e}. Stage 2 will match against the style image itself "
                  "(no stylized key views).", file=sys.stderr)
            return None
    return stylize_views(models, keyviews.rgb, keyviews.depth, style_image, cfg, alpha=keyviews.alpha)


# -- CLI helpers (used by `ssgwarp stylize`) ----------------------------------------------------------
def add_stage1_arguments(parser) -> None:
    """Stage 1 options for a subcommand's parser (weights paths, steps, guidance, IP-Adapter, CVSA)."""
    g = parser.add_argument_group("Stage 1 (diffusion key views)")
    g.add_argument("--sd15", default=None,
                   help="SD1.5 diffusers folder (default: SSGWARP_SD15, $SSGWARP_WEIGHTS, the Hugging Face cache, "
                        "else downloaded; see `ssgwarp weights`)")
    g.add_argument("--controlnet-depth", default=None, help="depth ControlNet diffusers folder (default: found "
                                                            "or downloaded like --sd15)")
    g.add_argument("--ip-adapter", default=None, help="ip-adapter_sd15.safetensors (default: found or downloaded)")
    g.add_argument("--image-encoder", default=None,
                   help="IP-Adapter CLIP image encoder folder (default: found or downloaded)")
    g.add_argument("--prompt", default="", help="style prompt (the style image goes through IP-Adapter)")
    g.add_argument("--negative-prompt", default="", help="negative prompt")
    g.add_argument("--steps", type=int, default=50, help="DDIM steps for inversion and denoising (default 50)")
    g.add_argument("--strength", type=float, default=1.0, help="fraction of the schedule inverted (default 1)")
    g.add_argument("--guidance", type=float, default=7.5, help="classifier-free guidance scale (default 7.5)")
    g.add_argument("--controlnet-scale", type=float, default=1.0, help="depth ControlNet scale (default 1)")
    g.add_argument("--ip-scale", type=float, default=1.0, help="IP-Adapter scale (default 1)")
    g.add_argument("--ip-block-scale", action="append", default=None, metavar="PREFIX=S",
                   help="per-block IP-Adapter scale, e.g. up_blocks.1.attentions.1=1.0 (repeatable)")
    g.add_argument("--no-cvsa", action="store_true", help="turn Cross-View Style Alignment off")
    g.add_argument("--cvsa-blocks", default="last",
                   help="comma-separated UNet blocks carrying CVSA (default last = up_blocks.3)")
    g.add_argument("--cvsa-views-per-call", type=int, default=None,
                   help="query views per attention call (memory; default all)")
    g.add_argument("--eta", type=float, default=0.0, help="DDIM eta (0 = deterministic)")
    g.add_argument("--stage1-dtype", default="auto", choices=("auto", "fp16", "bf16", "fp32"),
                   help="model precision (auto: fp16 on CUDA, fp32 on CPU)")


def config_from_args(args) -> Stage1Config:
    """Stage1Config from the options of :func:`add_stage1_arguments` (+ ``--seed`` and config ``weights``)."""
    blocks = {}
    for item in getattr(args, "ip_block_scale", None) or []:
        name, sep, val = str(item).partition("=")
        try:
            blocks[name.strip()] = float(val)
        except ValueError:
            sep = ""
        if not sep:
            raise InputError(f"--ip-block-scale '{item}': expected PREFIX=SCALE, e.g. up_blocks.1.attentions.1=1.0")
    weights = getattr(args, "weights", None)
    return Stage1Config(
        sd15=args.sd15, controlnet_depth=args.controlnet_depth, ip_adapter=args.ip_adapter,
        image_encoder=args.image_encoder, weights=weights if isinstance(weights, Mapping) else None,
        prompt=args.prompt, negative_prompt=args.negative_prompt, steps=args.steps, strength=args.strength,
        guidance=args.guidance, controlnet_scale=args.controlnet_scale, ip_adapter_scale=args.ip_scale,
        ip_adapter_block_scales=blocks, cvsa=not args.no_cvsa,
        cvsa_blocks=tuple(b.strip() for b in str(args.cvsa_blocks).split(",") if b.strip()),
        cvsa_views_per_call=args.cvsa_views_per_call, eta=args.eta, seed=int(getattr(args, "seed", 0)),
        dtype=args.stage1_dtype).validate()
