"""Stand-ins for pretrained weights, for tests and benchmarks: no weights, no network.

* random-weight Stage 1 modules (:func:`random_stage1_components`, tiny or at SD1.5 size)
  and a random IP-Adapter state (:func:`random_ip_adapter_state`);
* the same saved in the real file formats: diffusers / transformers ``save_pretrained``
  folders and the IP-Adapter safetensors (:func:`save_stage1`);
* a Hugging Face Hub cache in the real layout (``models--ORG--NAME/blobs/<hash>``,
  ``snapshots/REV/... -> ../../blobs/<hash>``, ``refs/main``; :func:`hf_cache_entry`,
  :func:`fake_hf_cache`) and a torch hub checkpoints folder with torchvision-layout
  state dicts (:func:`fake_torch_hub`);
* a tiny Segment Anything model saved as a transformers ``SamModel`` folder (:func:`save_tiny_sam`).

Benchmarks import it with ``sys.path.insert(0, ".../tests")``.
"""
from __future__ import annotations

import hashlib
import math
import os
import shutil
from pathlib import Path
from typing import Mapping, Optional

import torch

from ssgwarp.errors import InputError

FAKE_REVISION = "0123456789abcdef0123456789abcdef01234567"
_LFS_SUFFIXES = (".safetensors", ".bin", ".pth", ".pt", ".ckpt", ".h5")


# -- random-weight modules ---------------------------------------------------------------------------------
def _tiny_tokenizer():
    from transformers import CLIPTokenizer

    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for c in "abcdefghijklmnopqrstuvwxyz":
        vocab[c] = len(vocab)
    for c in "abcdefghijklmnopqrstuvwxyz":
        vocab[c + "</w>"] = len(vocab)
    return CLIPTokenizer(vocab=vocab, merges=[])


def random_stage1_components(arch: str = "tiny", seed: int = 0, device="cpu") -> dict:
    """Randomly initialised Stage 1 modules (no weights, no network) for tests and benchmarks.

    ``arch="tiny"``: a 2-level UNet (32, 64 channels, attention in every block),
    a VAE with the SD factor 8, 1-layer CLIP encoders; runs on a CPU core in
    milliseconds. ``arch="sd15"``: the SD1.5 / ControlNet / ViT-L text / ViT-H
    image-encoder architectures at full size (timings only). The ControlNet's
    zero-initialised output convolutions get small random weights so the depth
    condition has an effect. ``ip_state`` is a random IP-Adapter state dict.
    """
    from diffusers import AutoencoderKL, ControlNetModel, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPVisionConfig, CLIPVisionModelWithProjection

    torch.manual_seed(seed)
    with torch.device(device):
        if arch == "tiny":
            unet = UNet2DConditionModel(
                sample_size=8, in_channels=4, out_channels=4, block_out_channels=(32, 64), layers_per_block=1,
                down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D"),
                up_block_types=("CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
                cross_attention_dim=32, attention_head_dim=8, norm_num_groups=32)
            # scaling_factor 3: latents of roughly unit spread, as SD1.5's 0.18215 gives its VAE
            vae = AutoencoderKL(in_channels=3, out_channels=3, block_out_channels=(8, 16, 16, 16),
                                down_block_types=("DownEncoderBlock2D",) * 4,
                                up_block_types=("UpDecoderBlock2D",) * 4, latent_channels=4,
                                norm_num_groups=8, layers_per_block=1, sample_size=64, scaling_factor=3.0)
            controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 8, 16, 16))
            tokenizer = _tiny_tokenizer()
            text_encoder = CLIPTextModel(CLIPTextConfig(
                vocab_size=len(tokenizer.get_vocab()), hidden_size=32, intermediate_size=37, num_hidden_layers=1,
                num_attention_heads=4, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
                pad_token_id=1))
            image_encoder = CLIPVisionModelWithProjection(CLIPVisionConfig(
                hidden_size=32, intermediate_size=37, num_hidden_layers=1, num_attention_heads=4, image_size=32,
                patch_size=8, projection_dim=16))
        elif arch == "sd15":
            unet = UNet2DConditionModel(
                sample_size=64, cross_attention_dim=768, attention_head_dim=8,
                block_out_channels=(320, 640, 1280, 1280), layers_per_block=2,
                down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
                up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
            vae = AutoencoderKL(in_channels=3, out_channels=3, block_out_channels=(128, 256, 512, 512),
                                down_block_types=("DownEncoderBlock2D",) * 4,
                                up_block_types=("UpDecoderBlock2D",) * 4, latent_channels=4,
                                layers_per_block=2, sample_size=512)
            controlnet = ControlNetModel.from_unet(unet)
            tokenizer = _tiny_tokenizer()   # timings only: token ids are padded to 77 anyway
            text_encoder = CLIPTextModel(CLIPTextConfig(
                vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                num_attention_heads=12, max_position_embeddings=77, hidden_act="quick_gelu",
                projection_dim=768, bos_token_id=0, eos_token_id=1, pad_token_id=1))
            image_encoder = CLIPVisionModelWithProjection(CLIPVisionConfig(
                hidden_size=1280, intermediate_size=5120, num_hidden_layers=32, num_attention_heads=16,
                image_size=224, patch_size=14, projection_dim=1024, hidden_act="gelu"))
        else:
            raise InputError(f"unknown random architecture '{arch}' (tiny or sd15)")
        g = torch.Generator(device="cpu").manual_seed(seed + 1)
        if arch == "tiny":
            # a random UNet amplifies input changes ~4x; a trained noise predictor is far gentler. Scaling
            # the output keeps the tiny model in the regime where DDIM inversion is meaningful.
            with torch.no_grad():
                unet.conv_out.weight.mul_(0.1)
                unet.conv_out.bias.mul_(0.1)
        for mod in [controlnet.controlnet_down_blocks, controlnet.controlnet_mid_block,
                    controlnet.controlnet_cond_embedding.conv_out]:
            for p in mod.parameters():
                p.data.copy_(torch.randn(p.shape, generator=g, device="cpu") * 0.02)
    scheduler = DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                              clip_sample=False, set_alpha_to_one=False, steps_offset=1)
    ip_state = random_ip_adapter_state(unet, image_encoder.config.projection_dim, seed=seed + 2)
    return dict(unet=unet, vae=vae, controlnet=controlnet, scheduler=scheduler, text_encoder=text_encoder,
                tokenizer=tokenizer, image_encoder=image_encoder, ip_state=ip_state)


def random_ip_adapter_state(unet, image_embed_dim: int, seed: int = 0, num_tokens: int = 4) -> dict:
    """A random IP-Adapter (SD1.5 layout) state dict for ``unet``: ``image_proj.proj/norm`` and
    ``ip_adapter.{2i+1}.to_k_ip/to_v_ip`` for the i-th cross-attention layer."""
    g = torch.Generator().manual_seed(seed)
    cross = int(unet.config.cross_attention_dim)
    image_proj = {
        "proj.weight": torch.randn(num_tokens * cross, image_embed_dim, generator=g) / math.sqrt(image_embed_dim),
        "proj.bias": torch.zeros(num_tokens * cross),
        "norm.weight": torch.ones(cross), "norm.bias": torch.zeros(cross),
    }
    ip = {}
    boc = list(unet.config.block_out_channels)
    key_id = 1
    for name in unet.attn_processors:
        if name.endswith("attn1.processor"):
            continue
        if name.startswith("mid_block"):
            hidden = boc[-1]
        elif name.startswith("up_blocks"):
            hidden = list(reversed(boc))[int(name.split(".")[1])]
        else:
            hidden = boc[int(name.split(".")[1])]
        ip[f"{key_id}.to_k_ip.weight"] = torch.randn(hidden, cross, generator=g) / math.sqrt(cross)
        ip[f"{key_id}.to_v_ip.weight"] = torch.randn(hidden, cross, generator=g) / math.sqrt(cross)
        key_id += 2
    return {"image_proj": image_proj, "ip_adapter": ip}


# -- CLI helpers (used by `ssgwarp stylize`) ----------------------------------------------------------


# -- real file formats -------------------------------------------------------------------------------------
def save_ip_adapter(ip_state: Mapping[str, Mapping[str, torch.Tensor]], path: str | os.PathLike) -> Path:
    """The IP-Adapter state as the published ``ip-adapter_sd15.safetensors`` (keys ``image_proj.*``, ``ip_adapter.*``)."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    flat = {f"{part}.{k}": v.contiguous() for part in ("image_proj", "ip_adapter") for k, v in ip_state[part].items()}
    save_file(flat, str(path))
    return path


def save_stage1(comps: Mapping, root: str | os.PathLike) -> dict[str, Path]:
    """Save Stage 1 modules under ``root`` as the published repos lay them out; returns ``{weights key: path}``.

    ``sd15/`` (model_index.json, unet/, vae/, scheduler/, text_encoder/, tokenizer/),
    ``controlnet/``, ``ip-adapter/models/ip-adapter_sd15.safetensors`` and
    ``ip-adapter/models/image_encoder/``.
    """
    import json

    root = Path(root)
    sd = root / "sd15"
    for name in ("unet", "vae", "scheduler", "text_encoder", "tokenizer"):
        comps[name].save_pretrained(sd / name)
    (sd / "model_index.json").write_text(json.dumps({
        "_class_name": "StableDiffusionPipeline", "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"], "scheduler": ["diffusers", "DDIMScheduler"],
        "text_encoder": ["transformers", "CLIPTextModel"], "tokenizer": ["transformers", "CLIPTokenizer"]}))
    comps["controlnet"].save_pretrained(root / "controlnet")
    comps["image_encoder"].save_pretrained(root / "ip-adapter" / "models" / "image_encoder")
    ip = save_ip_adapter(comps["ip_state"], root / "ip-adapter" / "models" / "ip-adapter_sd15.safetensors")
    return {"sd15": sd, "controlnet_depth": root / "controlnet", "ip_adapter": ip,
            "image_encoder": root / "ip-adapter" / "models" / "image_encoder"}


def save_tiny_sam(path: str | os.PathLike, seed: int = 0) -> Path:
    """A tiny random ``transformers.SamModel`` (64 px input, 16-d embeddings) + its image processor config."""
    from transformers import SamConfig, SamModel

    try:
        from transformers import SamImageProcessorPil as Processor
    except ImportError:  # older transformers
        from transformers import SamImageProcessor as Processor
    torch.manual_seed(seed)
    cfg = SamConfig(
        vision_config=dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                           image_size=64, patch_size=16, output_channels=16, global_attn_indexes=[1], window_size=2,
                           mlp_dim=64, num_pos_feats=8),
        prompt_encoder_config=dict(hidden_size=16, image_size=64, patch_size=16, mask_input_channels=4),
        mask_decoder_config=dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, mlp_dim=32,
                                 iou_head_hidden_dim=16, iou_head_depth=2, num_multimask_outputs=3))
    path = Path(path)
    SamModel(cfg).save_pretrained(path)
    Processor(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64}).save_pretrained(path)
    return path


def vgg16_state(upto: str = "relu3_3", seed: int = 0) -> dict[str, torch.Tensor]:
    """A random torchvision VGG16 state dict (``features.N.weight/bias``, the real shapes) up to layer ``upto``."""
    from ssgwarp.evaluation.features import VGG16Features

    torch.manual_seed(seed)
    return {f"features.{k}": v for k, v in VGG16Features(layers=[upto]).features.state_dict().items()}


# -- caches in the real layouts -----------------------------------------------------------------------------
def _git_blob_sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


def hf_cache_entry(cache: str | os.PathLike, repo: str, files: Mapping[str, str | os.PathLike],
                   revision: str = FAKE_REVISION) -> Path:
    """Add ``files`` (``{path in the repo: local file}``) to the Hugging Face cache ``cache`` as the hub does.

    Blobs are named by SHA-256 (large, LFS-stored kinds of file) or by their git
    object id (small files); the snapshot holds relative links to them and
    ``refs/main`` names the revision. Returns the snapshot folder.
    """
    base = Path(cache) / ("models--" + repo.replace("/", "--"))
    snap = base / "snapshots" / revision
    (base / "blobs").mkdir(parents=True, exist_ok=True)
    (base / "refs").mkdir(parents=True, exist_ok=True)
    (base / "refs" / "main").write_text(revision)
    for rel, src in files.items():
        data = Path(src).read_bytes()
        name = hashlib.sha256(data).hexdigest() if rel.endswith(_LFS_SUFFIXES) else _git_blob_sha1(data)
        blob = base / "blobs" / name
        if not blob.exists():
            blob.write_bytes(data)
        link = snap / rel
        link.parent.mkdir(parents=True, exist_ok=True)
        if link.is_symlink() or link.exists():
            link.unlink()
        os.symlink(os.path.relpath(blob, link.parent), link)
    return snap


def _tree(folder: Path, prefix: str = "") -> dict[str, Path]:
    return {prefix + str(p.relative_to(folder)): p for p in sorted(folder.rglob("*")) if p.is_file()}


def fake_hf_cache(cache: str | os.PathLike, saved: Mapping[str, Path], sam: Optional[Path] = None) -> Path:
    """The Stage 1 folders of :func:`save_stage1` (and a SAM folder) as Hugging Face cache entries
    of the public repos (``stable-diffusion-v1-5/stable-diffusion-v1-5``, ...). Returns ``cache``."""
    from ssgwarp.services.weight_specs import SPECS

    cache = Path(cache)
    hf_cache_entry(cache, SPECS["sd15"].repo, _tree(saved["sd15"]))
    hf_cache_entry(cache, SPECS["controlnet_depth"].repo, _tree(saved["controlnet_depth"]))
    hf_cache_entry(cache, "h94/IP-Adapter", {"models/ip-adapter_sd15.safetensors": saved["ip_adapter"],
                                            **_tree(saved["image_encoder"], "models/image_encoder/")})
    if sam is not None:
        hf_cache_entry(cache, SPECS["sam"].repo, _tree(sam))
    return cache


def fake_torch_hub(torch_home: str | os.PathLike, vgg: Optional[dict] = None, raft: Optional[dict] = None) -> Path:
    """State dicts saved as torchvision names them in ``TORCH_HOME/hub/checkpoints``; returns that folder."""
    from ssgwarp.services.weight_specs import SPECS

    ck = Path(torch_home) / "hub" / "checkpoints"
    ck.mkdir(parents=True, exist_ok=True)
    for key, state in (("vgg16", vgg), ("raft", raft)):
        if state is not None:
            torch.save(state, ck / SPECS[key].filename)
    return ck


def copy_tree(src: str | os.PathLike, dst: str | os.PathLike) -> Path:
    """Copy a fake cache (links kept as links) to corrupt one file without touching the original."""
    shutil.copytree(src, dst, symlinks=True)
    return Path(dst)
