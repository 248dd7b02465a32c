"""Stage 1's models: configuration, weights lookup and loading, IP-Adapter (:mod:`ssgwarp.stylization.diffusion` runs them).

:class:`Stage1Config` (weights paths, sampler and guidance settings), :class:`Stage1Models` (the
loaded modules), :func:`missing_weights` / :func:`load_stage1` (through :mod:`ssgwarp.services.weights`),
:func:`assemble_stage1` (from modules built elsewhere, e.g. the tests' random-weight stand-ins in
``tests/fakeweights.py``), the IP-Adapter state's reading and loading into a diffusers UNet, and the
CLIP preprocessing of the style image.

diffusers and transformers are imported inside the functions that load models: they are optional
(the ``diffusion`` extra) and slow to import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch

from ..services import weights as W
from ..services.weight_specs import SPECS
from ..errors import InputError, SsgwarpError, WeightsNotFound

WEIGHT_KEYS = ("sd15", "controlnet_depth", "ip_adapter", "image_encoder")
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


# -- configuration ------------------------------------------------------------------------------
@dataclass
class Stage1Config:
    """Stage 1 options.

    Weights: ``sd15``, ``controlnet_depth``, ``ip_adapter``, ``image_encoder``
    are explicit paths (None: look them up, see :mod:`ssgwarp.services.weights`);
    ``weights`` is the config file's ``weights`` mapping.
    ``steps``: DDIM steps (inversion and denoising each); ``strength`` in (0, 1]:
    fraction of the schedule used; ``guidance``: CFG scale; ``controlnet_scale``;
    ``ip_adapter_scale``: IP-Adapter scale on every cross-attention layer, except
    where ``ip_adapter_block_scales`` maps a processor-name prefix (e.g.
    ``"up_blocks.1.attentions.1"`` or ``"down_blocks.2"``) to another scale
    (longest prefix wins); ``cvsa`` on/off, ``cvsa_blocks`` (``"last"`` = the last
    up-sampling block, ``up_blocks.3`` on SD1.5), ``cvsa_views_per_call`` (memory);
    ``prompt``/``negative_prompt``; ``eta``: DDIM stochasticity (0 = deterministic);
    ``seed``; ``dtype``: ``auto`` (fp16 on CUDA, fp32 on CPU), ``fp16``, ``bf16`` or ``fp32``.
    """

    sd15: Optional[str] = None
    controlnet_depth: Optional[str] = None
    ip_adapter: Optional[str] = None
    image_encoder: Optional[str] = None
    weights: Optional[Mapping[str, str]] = None
    prompt: str = ""
    negative_prompt: str = ""
    steps: int = 50
    strength: float = 1.0
    guidance: float = 7.5
    controlnet_scale: float = 1.0
    ip_adapter_scale: float = 1.0
    ip_adapter_block_scales: dict = field(default_factory=dict)
    cvsa: bool = True
    cvsa_blocks: tuple = ("last",)
    cvsa_views_per_call: Optional[int] = None
    eta: float = 0.0
    seed: int = 0
    dtype: str = "auto"
    progress: bool = True

    def validate(self) -> "Stage1Config":
        if int(self.steps) < 1:
            raise InputError(f"Stage 1 steps must be >= 1, got {self.steps}")
        if not 0.0 < float(self.strength) <= 1.0:
            raise InputError(f"Stage 1 strength must be in (0, 1], got {self.strength}")
        if float(self.eta) < 0.0:
            raise InputError(f"Stage 1 eta must be >= 0, got {self.eta}")
        if self.dtype not in ("auto", "fp16", "bf16", "fp32"):
            raise InputError(f"Stage 1 dtype '{self.dtype}': expected auto, fp16, bf16 or fp32")
        for k, v in dict(self.ip_adapter_block_scales or {}).items():
            if not isinstance(v, (int, float)):
                raise InputError(f"ip_adapter_block_scales['{k}'] must be a number, got {v!r}")
        return self

    def torch_dtype(self, device) -> torch.dtype:
        device = torch.device(device)
        if self.dtype == "auto":
            return torch.float16 if device.type == "cuda" else torch.float32
        return {"fp16": torch.float16, "bf16": torch.bfloat16, "fp32": torch.float32}[self.dtype]


@dataclass
class Stage1Models:
    """The modules Stage 1 runs (IP-Adapter already loaded into ``unet``)."""

    unet: Any
    vae: Any
    controlnet: Any
    scheduler: Any
    text_encoder: Any
    tokenizer: Any
    image_encoder: Any
    device: torch.device
    dtype: torch.dtype

    @property
    def vae_scale_factor(self) -> int:
        return 2 ** (len(self.vae.config.block_out_channels) - 1)

    @property
    def has_ip_adapter(self) -> bool:
        return getattr(self.unet.config, "encoder_hid_dim_type", None) == "ip_image_proj"

    @torch.no_grad()
    def encode_prompt(self, prompts: Sequence[str]) -> torch.Tensor:
        """``[B, L, D]`` text embeddings (last hidden state of the CLIP text encoder)."""
        max_len = int(getattr(self.text_encoder.config, "max_position_embeddings", 77))
        ids = self.tokenizer(list(prompts), padding="max_length", max_length=max_len, truncation=True,
                             return_tensors="pt").input_ids.to(self.device)
        return self.text_encoder(ids)[0].to(self.dtype)

    @torch.no_grad()
    def encode_style(self, style: torch.Tensor) -> torch.Tensor:
        """``style [H, W, 3]`` in [0, 1] → CLIP image embedding ``[1, E]``."""
        size = int(self.image_encoder.config.image_size)
        px = clip_preprocess(style, size).to(self.device, self.image_encoder.dtype)
        return self.image_encoder(px).image_embeds.to(self.dtype)


def missing_weights(cfg: Stage1Config, download: Optional[bool] = None) -> list[str]:
    """One message per Stage 1 model that is neither on this machine nor fetched now (empty: all present).

    Models are found as :mod:`ssgwarp.services.weights` finds them (explicit path, config,
    environment, ``$SSGWARP_WEIGHTS``, the Hugging Face cache); a missing one is
    downloaded into the Hugging Face cache unless downloads are off (``download=False``,
    ``--offline``, ``HF_HUB_OFFLINE=1``, ...) or an explicit path is wrong.
    """
    found = {k: W.find(k, getattr(cfg, k), cfg.weights) for k in WEIGHT_KEYS}
    out = [W.message(k, getattr(cfg, k)) for k in WEIGHT_KEYS if found[k] is None and getattr(cfg, k)]
    if out:         # a wrong explicit path: report, fetch nothing
        return out + [W.message(k) for k in WEIGHT_KEYS if found[k] is None and not getattr(cfg, k)]
    for key in WEIGHT_KEYS:
        if found[key] is None:
            try:
                found[key] = W.require(key, None, cfg.weights, download=download)
            except WeightsNotFound as e:
                out.append(str(e))
                continue
        spec = SPECS[key]
        need = [f for f in spec.required if not (found[key] / f).exists()]
        if need:
            out.append(f"{found[key]} lacks {', '.join(need)}: {spec.expected} (from '{spec.source}')")
    return out


def _paths(cfg: Stage1Config) -> dict[str, Path]:
    missing = missing_weights(cfg)
    if missing:
        raise WeightsNotFound("Stage 1 needs local weights: " + " | ".join(missing))
    return {k: W.find(k, getattr(cfg, k), cfg.weights) for k in WEIGHT_KEYS}


def load_stage1(cfg: Stage1Config, device) -> Stage1Models:
    """Load the Stage 1 modules (``local_files_only=True``) from the paths :mod:`ssgwarp.services.weights` resolves.

    Missing models are downloaded first where allowed (:func:`missing_weights`).
    Raises :class:`WeightsNotFound` listing every missing piece when weights are
    absent, and :class:`~ssgwarp.errors.InputError` naming the file and how to
    fetch it again when one is truncated or corrupt.
    """
    W.check_kernels_package()
    from diffusers import AutoencoderKL, ControlNetModel, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer, CLIPVisionModelWithProjection

    cfg.validate()
    p = _paths(cfg)

    def load(key, what, fn, path, subfolder=None):
        try:
            if fn is read_ip_adapter:
                return fn(path)
            kw = {"subfolder": subfolder} if subfolder else {}
            return fn(str(path), local_files_only=True, **kw)
        except SsgwarpError:
            raise
        except Exception as e:  # truncated / corrupt / wrong files (OSError, SafetensorError, ValueError, ...)
            raise W.load_error(key, Path(path) / (subfolder or ""), e, what) from None

    sd = p["sd15"]
    comps = dict(
        unet=load("sd15", "the SD1.5 UNet", UNet2DConditionModel.from_pretrained, sd, "unet"),
        vae=load("sd15", "the SD1.5 VAE", AutoencoderKL.from_pretrained, sd, "vae"),
        scheduler=load("sd15", "the scheduler config", DDIMScheduler.from_pretrained, sd, "scheduler"),
        text_encoder=load("sd15", "the CLIP text encoder", CLIPTextModel.from_pretrained, sd, "text_encoder"),
        tokenizer=load("sd15", "the CLIP tokenizer", CLIPTokenizer.from_pretrained, sd, "tokenizer"),
        controlnet=load("controlnet_depth", "the depth ControlNet", ControlNetModel.from_pretrained,
                        p["controlnet_depth"]),
        image_encoder=load("image_encoder", "the IP-Adapter image encoder",
                           CLIPVisionModelWithProjection.from_pretrained, p["image_encoder"]),
        ip_state=load("ip_adapter", "the IP-Adapter weights", read_ip_adapter, p["ip_adapter"]),
    )
    return assemble_stage1(comps, device, cfg.torch_dtype(device))


def assemble_stage1(components: Mapping[str, Any], device, dtype: torch.dtype = torch.float32) -> Stage1Models:
    """Stage1Models from bare modules: ``unet, vae, controlnet, scheduler, text_encoder, tokenizer,
    image_encoder`` and ``ip_state`` (IP-Adapter state dict, loaded into the UNet; None: no IP-Adapter).

    The scheduler is converted to DDIM (same betas). Modules go to ``device``/``dtype`` in eval mode.
    """
    W.check_kernels_package()
    from diffusers import DDIMScheduler

    c = dict(components)
    device = torch.device(device)
    unet = c["unet"]
    if c.get("ip_state") is not None:
        load_ip_adapter(unet, c["ip_state"])
    sched = c["scheduler"]
    if not isinstance(sched, DDIMScheduler):
        sched = DDIMScheduler.from_config(sched.config)
    from diffusers.utils import logging as dlog

    mods = {}
    level = dlog.get_verbosity()
    dlog.set_verbosity_error()   # diffusers warns on every .to(dtype=...) about (no) fp32-only modules
    try:
        for k in ("unet", "vae", "controlnet", "text_encoder", "image_encoder"):
            m = unet if k == "unet" else c.get(k)
            if m is not None:
                m = m.to(device=device, dtype=dtype).eval()
                m.requires_grad_(False)
            mods[k] = m
    finally:
        dlog.set_verbosity(level)
    return Stage1Models(mods["unet"], mods["vae"], mods["controlnet"], sched, mods["text_encoder"],
                        c["tokenizer"], mods["image_encoder"], device, dtype)


# -- IP-Adapter ---------------------------------------------------------------------------------
def read_ip_adapter(path: str | Path) -> dict:
    """IP-Adapter weights file → ``{"image_proj": {...}, "ip_adapter": {...}}`` (safetensors or torch)."""
    path = Path(path)
    if not path.is_file():
        raise WeightsNotFound(f"IP-Adapter weights {path} not found")
    if path.suffix == ".safetensors":
        from safetensors import safe_open

        sd = {"image_proj": {}, "ip_adapter": {}}
        with safe_open(str(path), framework="pt", device="cpu") as f:
            for key in f.keys():
                head, _, rest = key.partition(".")
                if head in sd:
                    sd[head][rest] = f.get_tensor(key)
    else:
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
    if not isinstance(sd, dict) or not sd.get("image_proj") or not sd.get("ip_adapter"):
        raise InputError(f"{path}: not an IP-Adapter weights file (needs image_proj.* and ip_adapter.* tensors)")
    return sd


def load_ip_adapter(unet, state: Mapping[str, Any] | str | Path) -> None:
    """Load IP-Adapter weights into ``unet`` with diffusers' ``_load_ip_adapter_weights``.

    Every cross-attention processor becomes an ``IPAdapterAttnProcessor2_0``
    holding the image key/value projections; the image projection goes to
    ``unet.encoder_hid_proj`` and the UNet then expects
    ``added_cond_kwargs={"image_embeds": [embeds [B, 1, E]]}``.
    """
    if not isinstance(state, Mapping):
        state = read_ip_adapter(state)
    n_cross = sum(1 for n in unet.attn_processors if n.endswith("attn2.processor"))
    have = {k for k in state["ip_adapter"] if k.endswith("to_k_ip.weight")}
    if len(have) != n_cross:
        raise InputError(f"IP-Adapter weights have {len(have)} cross-attention layers, the UNet has {n_cross} "
                         "(IP-Adapter for another base model?)")
    from diffusers.utils import logging as dlog

    level = dlog.get_verbosity()
    dlog.set_verbosity_error()   # it casts with .to(dtype=...), which logs a spurious float32 warning
    try:
        unet._load_ip_adapter_weights([dict(state)], low_cpu_mem_usage=False)
    except (KeyError, RuntimeError) as e:
        raise InputError(f"IP-Adapter weights do not fit this UNet: {str(e).splitlines()[0]}") from None
    finally:
        dlog.set_verbosity(level)


def set_ip_adapter_scales(unet, scale: float = 1.0, block_scales: Optional[Mapping[str, float]] = None
                          ) -> dict[str, float]:
    """Set the IP-Adapter scale of every IP-Adapter processor; returns ``{processor name: scale}``.

    ``block_scales`` maps processor-name prefixes to scales; the longest matching
    prefix wins, other layers get ``scale``.
    """
    from diffusers.models.attention_processor import IPAdapterAttnProcessor, IPAdapterAttnProcessor2_0

    block_scales = dict(block_scales or {})
    out = {}
    for name, proc in unet.attn_processors.items():
        if isinstance(proc, (IPAdapterAttnProcessor, IPAdapterAttnProcessor2_0)):
            hits = [p for p in block_scales if name == p or name.startswith(p.rstrip(".") + ".")]
            s = float(block_scales[max(hits, key=len)]) if hits else float(scale)
            proc.scale = [s] * len(proc.scale)
            out[name] = s
    unknown = [p for p in block_scales if not any(n == p or n.startswith(p.rstrip(".") + ".") for n in out)]
    if unknown:
        raise InputError(f"ip_adapter_block_scales: no IP-Adapter layer under {unknown} "
                         "(use prefixes such as down_blocks.2 or up_blocks.1.attentions.1)")
    return out


def clip_preprocess(img, size: int) -> torch.Tensor:
    """CLIP image preprocessing: shorter side to ``size`` (bicubic), centre crop, normalise → ``[1,3,size,size]``."""
    import torch.nn.functional as F

    t = torch.as_tensor(np.asarray(img) if not isinstance(img, torch.Tensor) else img).float()
    if t.ndim != 3 or t.shape[-1] not in (3, 4):
        raise InputError(f"style image must be [H, W, 3], got shape {tuple(t.shape)}")
    x = t[..., :3].permute(2, 0, 1)[None].clamp(0, 1)
    h, w = x.shape[-2:]
    s = size / min(h, w)
    nh, nw = max(size, int(round(h * s))), max(size, int(round(w * s)))
    x = F.interpolate(x, size=(nh, nw), mode="bicubic", align_corners=False, antialias=True).clamp(0, 1)
    top, left = (nh - size) // 2, (nw - size) // 2
    x = x[..., top:top + size, left:left + size]
    mean = torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(CLIP_STD).view(1, 3, 1, 1)
    return (x - mean) / std
