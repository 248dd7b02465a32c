"""The pretrained models ssgwarp knows (:data:`SPECS`: local routes, public id, files, size,
licence, published hash), the names of sets of them (:data:`GROUPS`) and the hashes a file is
checked against. Where they are found and how they are fetched: :mod:`ssgwarp.services.weights`, which
re-exports these names.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from ..errors import InputError


@dataclass(frozen=True)
class WeightSpec:
    """One pretrained model: local routes, public id, approximate size and licence.

    ``repo`` (Hugging Face id) + ``files`` (paths in the repo that must all be
    cached; ``a|b``: either, the first the repo has is downloaded; ``patterns``
    are downloaded, default ``files``) + ``subfolder`` /
    ``filename`` (what :func:`find` returns inside the snapshot); or ``url`` +
    ``filename`` (a torch hub checkpoints file, ``sha256`` its published hash
    or hash prefix). ``required``: entries a folder must hold (checked in user
    folders too).
    """

    key: str                 # config key and name used in messages and on the command line
    title: str               # what it is, in words
    env: str                 # environment variable
    default: str             # sub-path under $SSGWARP_WEIGHTS
    expected: str            # what must be there (messages)
    source: str              # public model name
    is_dir: bool = True
    repo: Optional[str] = None
    files: tuple[str, ...] = ()
    patterns: tuple[str, ...] = ()
    subfolder: str = ""
    filename: Optional[str] = None
    url: Optional[str] = None
    sha256: Optional[str] = None
    size: int = 0            # approximate download size in bytes (when the hub's metadata is unreachable)
    licence: str = ""
    flags: str = ""          # CLI options that take its path
    used_by: str = ""
    required: tuple[str, ...] = ()


_SD15_FILES = ("model_index.json", "unet/config.json", "unet/diffusion_pytorch_model.safetensors",
               "vae/config.json", "vae/diffusion_pytorch_model.safetensors", "scheduler/scheduler_config.json",
               "text_encoder/config.json", "text_encoder/model.safetensors", "tokenizer/tokenizer_config.json")

SPECS: dict[str, WeightSpec] = {s.key: s for s in [
    WeightSpec("sd15", "Stable Diffusion v1.5 (UNet, VAE, CLIP text encoder, tokenizer, scheduler)", "SSGWARP_SD15",
               "stable-diffusion-v1-5",
               "a diffusers folder: model_index.json, unet/, vae/, scheduler/, text_encoder/ and tokenizer/",
               "stable-diffusion-v1-5/stable-diffusion-v1-5", repo="stable-diffusion-v1-5/stable-diffusion-v1-5",
               files=_SD15_FILES, patterns=_SD15_FILES + ("tokenizer/*",), size=4_270_000_000,
               licence="CreativeML OpenRAIL-M", flags="--sd15", used_by="stylize Stage 1",
               required=("unet/config.json", "vae/config.json", "scheduler/scheduler_config.json",
                         "text_encoder/config.json", "tokenizer")),
    WeightSpec("controlnet_depth", "ControlNet v1.1 depth for SD1.5", "SSGWARP_CONTROLNET_DEPTH",
               "control_v11f1p_sd15_depth",
               "a diffusers ControlNet folder: config.json and diffusion_pytorch_model.safetensors",
               "lllyasviel/control_v11f1p_sd15_depth", repo="lllyasviel/control_v11f1p_sd15_depth",
               files=("config.json", "diffusion_pytorch_model.safetensors|diffusion_pytorch_model.bin"),
               size=1_450_000_000,
               licence="OpenRAIL", flags="--controlnet-depth", used_by="stylize Stage 1",
               required=("config.json",)),
    WeightSpec("ip_adapter", "IP-Adapter for SD1.5", "SSGWARP_IP_ADAPTER", "ip-adapter/ip-adapter_sd15.safetensors",
               "the IP-Adapter SD1.5 weights file ip-adapter_sd15.safetensors (or .bin)",
               "h94/IP-Adapter (models/ip-adapter_sd15.safetensors)", is_dir=False, repo="h94/IP-Adapter",
               files=("models/ip-adapter_sd15.safetensors",), filename="models/ip-adapter_sd15.safetensors",
               size=44_600_000, licence="Apache-2.0", flags="--ip-adapter", used_by="stylize Stage 1"),
    WeightSpec("image_encoder", "IP-Adapter image encoder (CLIP ViT-H/14 vision)", "SSGWARP_IMAGE_ENCODER",
               "ip-adapter/image_encoder",
               "a transformers CLIPVisionModelWithProjection folder: config.json and model.safetensors",
               "h94/IP-Adapter (models/image_encoder)", repo="h94/IP-Adapter", subfolder="models/image_encoder",
               files=("models/image_encoder/config.json", "models/image_encoder/model.safetensors"),
               size=2_530_000_000, licence="Apache-2.0", flags="--image-encoder", used_by="stylize Stage 1",
               required=("config.json",)),
    WeightSpec("vgg16", "VGG16 ImageNet features (torchvision VGG16_Weights.IMAGENET1K_V1)", "SSGWARP_VGG16",
               "vgg16.pth",
               "a torchvision VGG16 state dict (keys features.N.weight/bias), e.g. vgg16-397923af.pth",
               "torchvision.models.VGG16_Weights.IMAGENET1K_V1", is_dir=False,
               url="https://download.pytorch.org/models/vgg16-397923af.pth", filename="vgg16-397923af.pth",
               sha256="397923af", size=553_433_881, licence="BSD-3-Clause (torchvision; ImageNet-trained)",
               flags="--vgg16 (stylize), --vgg (evaluate)", used_by="stylize Stage 2 features, evaluate, LPIPS"),
    WeightSpec("raft", "RAFT-large optical flow (torchvision Raft_Large_Weights.C_T_SKHT_V2)", "SSGWARP_RAFT",
               "raft_large.pth",
               "a torchvision RAFT-large state dict, e.g. raft_large_C_T_SKHT_V2-ff5fadd5.pth",
               "torchvision.models.optical_flow.Raft_Large_Weights.C_T_SKHT_V2", is_dir=False,
               url="https://download.pytorch.org/models/raft_large_C_T_SKHT_V2-ff5fadd5.pth",
               filename="raft_large_C_T_SKHT_V2-ff5fadd5.pth", sha256="ff5fadd5", size=21_107_000,
               licence="BSD-3-Clause (torchvision)", flags="--raft", used_by="evaluate (flow warp)"),
    WeightSpec("lpips", "LPIPS v0.1 linear heads for VGG", "SSGWARP_LPIPS", "lpips_vgg.pth",
               "the LPIPS linear-layer weights for VGG (vgg.pth from the lpips package) next to vgg16.pth",
               "richzhang/PerceptualSimilarity (lpips/weights/v0.1/vgg.pth, also in the lpips package)",
               is_dir=False,
               url="https://github.com/richzhang/PerceptualSimilarity/raw/master/lpips/weights/v0.1/vgg.pth",
               filename="lpips_vgg_v0.1-a78928a0.pth",
               sha256="a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868", size=7_289,
               licence="BSD-2-Clause (lpips)", flags="--lpips", used_by="evaluate, reconstruct (LPIPS)"),
    WeightSpec("sam", "Segment Anything ViT-B (transformers SamModel)", "SSGWARP_SAM", "sam-vit-base",
               "a transformers SamModel folder: config.json, model.safetensors and preprocessor_config.json",
               "facebook/sam-vit-base", repo="facebook/sam-vit-base",
               files=("config.json", "model.safetensors", "preprocessor_config.json"), size=375_000_000,
               licence="Apache-2.0", flags="--sam", used_by="masks (instances for group)", required=("config.json",)),
]}

# names for sets of models on the command line (`ssgwarp weights --download stage1`)
GROUPS: dict[str, tuple[str, ...]] = {
    "stage1": ("sd15", "controlnet_depth", "ip_adapter", "image_encoder"),
    "evaluate": ("vgg16", "raft", "lpips"),
}


def _spec(key: str) -> WeightSpec:
    if key not in SPECS:
        raise InputError(f"unknown model '{key}': known models are {', '.join(SPECS)} "
                         f"(groups: {', '.join(GROUPS)})")
    return SPECS[key]


def _digest(path: Path, h) -> str:
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _sha256(path: Path) -> str:
    return _digest(path, hashlib.sha256())


def _git_blob_sha1(path: Path) -> str:
    """The git object id of a file (what the hub names the blobs of small, non-LFS files)."""
    return _digest(path, hashlib.sha1(f"blob {os.path.getsize(path)}\0".encode()))
