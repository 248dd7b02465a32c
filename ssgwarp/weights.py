"""Where pretrained weights live on this machine. Nothing is ever downloaded.

Each model is found, in order, from: an explicit path (CLI flag / API argument),
the config mapping (``--config FILE``, key ``weights``), the environment
variable named below, or ``$SSGWARP_WEIGHTS/<default subfolder>``. When none
exists, :func:`require` raises :class:`~ssgwarp.errors.WeightsNotFound` with the
expected files and the public model name to get them from, and
:func:`find` returns None so a stage that can run without them does.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional

from .errors import WeightsNotFound


@dataclass(frozen=True)
class WeightSpec:
    key: str            # config key and name used in messages
    env: str            # environment variable
    default: str        # sub-path under $SSGWARP_WEIGHTS
    expected: str       # what must be inside (for the error message)
    source: str         # public model name to get it from
    is_dir: bool = True
    hub: Optional[str] = None   # Hugging Face repo id also looked up in the local Hugging Face cache


SPECS: dict[str, WeightSpec] = {s.key: s for s in [
    WeightSpec("sd15", "SSGWARP_SD15", "stable-diffusion-v1-5",
               "a diffusers folder: model_index.json, unet/, vae/, scheduler/ (text_encoder/ and tokenizer/ for prompts)",
               "stable-diffusion-v1-5/stable-diffusion-v1-5"),
    WeightSpec("controlnet_depth", "SSGWARP_CONTROLNET_DEPTH", "control_v11f1p_sd15_depth",
               "a diffusers ControlNet folder: config.json and diffusion_pytorch_model.safetensors",
               "lllyasviel/control_v11f1p_sd15_depth"),
    WeightSpec("ip_adapter", "SSGWARP_IP_ADAPTER", "ip-adapter/ip-adapter_sd15.safetensors",
               "the IP-Adapter SD1.5 weights file ip-adapter_sd15.safetensors (or .bin)",
               "h94/IP-Adapter (models/ip-adapter_sd15.safetensors)", is_dir=False),
    WeightSpec("image_encoder", "SSGWARP_IMAGE_ENCODER", "ip-adapter/image_encoder",
               "a transformers CLIPVisionModelWithProjection folder: config.json and model.safetensors",
               "h94/IP-Adapter (models/image_encoder)"),
    WeightSpec("vgg16", "SSGWARP_VGG16", "vgg16.pth",
               "a torchvision VGG16 state dict (keys features.N.weight/bias), e.g. vgg16-397923af.pth",
               "torchvision.models.VGG16_Weights.IMAGENET1K_V1", is_dir=False),
    WeightSpec("raft", "SSGWARP_RAFT", "raft_large.pth",
               "a torchvision RAFT-large state dict, e.g. raft_large_C_T_SKHT_V2-ff5fadd5.pth",
               "torchvision.models.optical_flow.Raft_Large_Weights.C_T_SKHT_V2", is_dir=False),
    WeightSpec("lpips", "SSGWARP_LPIPS", "lpips_vgg.pth",
               "the LPIPS linear-layer weights for VGG (vgg.pth from the lpips package) next to vgg16.pth",
               "richzhang/PerceptualSimilarity (lpips/weights/v0.1/vgg.pth)", is_dir=False),
    WeightSpec("sam", "SSGWARP_SAM", "sam-vit-base",
               "a transformers SamModel folder: config.json and model.safetensors",
               "facebook/sam-vit-base", hub="facebook/sam-vit-base"),
]}


def hub_snapshot(repo_id: str) -> Optional[Path]:
    """The snapshot folder of ``repo_id`` in the local Hugging Face cache (``HF_HUB_CACHE``, else
    ``HF_HOME/hub``, else ``~/.cache/huggingface/hub``) that ``refs/main`` names, or None."""
    root = os.environ.get("HF_HUB_CACHE") or os.path.join(
        os.environ.get("HF_HOME") or os.path.join(os.path.expanduser("~"), ".cache", "huggingface"), "hub")
    repo = Path(root).expanduser() / ("models--" + repo_id.replace("/", "--"))
    try:
        rev = (repo / "refs" / "main").read_text().strip()
    except OSError:
        return None
    snap = repo / "snapshots" / rev
    return snap if rev and snap.is_dir() else None


def find(key: str, explicit: Optional[str | os.PathLike] = None,
         config: Optional[Mapping[str, str]] = None) -> Optional[Path]:
    """The local path of weights ``key`` if present, else None (never downloads)."""
    spec = SPECS[key]
    candidates: list[Path] = []
    if explicit:
        candidates.append(Path(explicit))
    if config and config.get(key):
        candidates.append(Path(config[key]))
    if os.environ.get(spec.env):
        candidates.append(Path(os.environ[spec.env]))
    if os.environ.get("SSGWARP_WEIGHTS"):
        candidates.append(Path(os.environ["SSGWARP_WEIGHTS"]) / spec.default)
    for c in candidates:
        c = c.expanduser()
        if (c.is_dir() if spec.is_dir else c.is_file()):
            return c
    if spec.hub and not explicit:
        return hub_snapshot(spec.hub)
    return None


def message(key: str, explicit: Optional[str | os.PathLike] = None) -> str:
    spec = SPECS[key]
    where = f"{explicit} does not exist; " if explicit else ""
    return (f"{where}no local weights for {key}: expected {spec.expected}; get them from '{spec.source}' "
            f"and pass the path, set {spec.env}, or put them at $SSGWARP_WEIGHTS/{spec.default}")


def require(key: str, explicit: Optional[str | os.PathLike] = None,
            config: Optional[Mapping[str, str]] = None) -> Path:
    """Like :func:`find` but raises :class:`WeightsNotFound` naming the expected files."""
    p = find(key, explicit, config)
    if p is None:
        raise WeightsNotFound(message(key, explicit))
    return p
