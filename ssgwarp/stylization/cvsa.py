"""Cross-View Style Alignment (CVSA): self-attention shared across key views.

During Stage 1 the K key views are denoised together in one UNet batch. On the
self-attention layers (``attn1``) of the chosen UNet blocks — by default the
last up-sampling block (``up_blocks.3`` of SD1.5) — :class:`CVSAProcessor`
replaces plain self-attention: the queries of every view attend to the keys and
values of *all* K views, concatenated along the token axis::

    out_v = softmax(Q_v [K_1 .. K_K]^T / sqrt(d)) [V_1 .. V_K]      (per head)

so the same content is styled the same way in every view.

Batch layout. The UNet batch holds ``G * K`` samples: G consecutive groups of
the K views, e.g. ``[uncond_1..uncond_K, cond_1..cond_K]`` under
classifier-free guidance (G = 2, the diffusers order of ``torch.cat([x, x])``)
or just the K views (G = 1). Attention is shared only *within* a group, so the
unconditional and conditional halves of CFG never see each other's tokens.

Memory. ``views_per_call`` query views go through one
``scaled_dot_product_attention`` call against all K views' keys/values (the
attention matrix is ``views_per_call*N x K*N`` per head, N tokens per view);
the result does not depend on it.

Installation works by processor name through ``unet.attn_processors`` /
``unet.set_attn_processor``; every other processor (notably IP-Adapter's on
the cross-attention ``attn2`` layers) is passed back unchanged, and
:func:`remove_cvsa` restores the processors CVSA replaced.
"""
from __future__ import annotations

import contextlib
from typing import Iterator, Optional, Sequence

import torch
import torch.nn.functional as F

from ..errors import InputError

__all__ = ["CVSAProcessor", "install_cvsa", "remove_cvsa", "cvsa_names", "cvsa_enabled", "resolve_blocks"]


class CVSAProcessor:
    """Attention processor for ``attn1`` layers that shares keys/values across K views.

    Args:
        num_views: K, the number of key views in each group of the batch.
        views_per_call: how many query views share one attention call
            (None: all K; smaller saves memory, same result).
        base: the processor this one replaced (restored by :func:`remove_cvsa`).
    """

    def __init__(self, num_views: int, views_per_call: Optional[int] = None, base=None) -> None:
        if int(num_views) < 1:
            raise InputError(f"CVSA: num_views must be >= 1, got {num_views}")
        if views_per_call is not None and int(views_per_call) < 1:
            raise InputError(f"CVSA: views_per_call must be >= 1 or None, got {views_per_call}")
        self.num_views = int(num_views)
        self.views_per_call = None if views_per_call is None else int(views_per_call)
        self.base = base

    def __repr__(self) -> str:
        return f"CVSAProcessor(num_views={self.num_views}, views_per_call={self.views_per_call})"

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor] = None,
                 attention_mask: Optional[torch.Tensor] = None, temb: Optional[torch.Tensor] = None,
                 *args, **kwargs) -> torch.Tensor:
        """``hidden_states [B, N, C]`` (or ``[B, C, H, W]``) → same shape; ``B = G * num_views``."""
        if encoder_hidden_states is not None or attention_mask is not None:
            raise ValueError("CVSAProcessor is for self-attention (attn1) layers without attention masks")
        residual = hidden_states
        if attn.spatial_norm is not None:
            hidden_states = attn.spatial_norm(hidden_states, temb)
        input_ndim = hidden_states.ndim
        if input_ndim == 4:
            b4, c4, h4, w4 = hidden_states.shape
            hidden_states = hidden_states.view(b4, c4, h4 * w4).transpose(1, 2)
        if attn.group_norm is not None:
            hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)

        B, N, _ = hidden_states.shape
        K = self.num_views
        if B % K != 0:
            raise ValueError(f"CVSA: batch {B} is not a multiple of num_views={K} "
                             "(the batch must hold whole groups of the K key views)")
        G = B // K
        heads = attn.heads
        q = attn.to_q(hidden_states)
        k = attn.to_k(hidden_states)
        v = attn.to_v(hidden_states)
        d = k.shape[-1] // heads
        q = q.view(B, N, heads, d).transpose(1, 2)          # [B, h, N, d]
        k = k.view(B, N, heads, d).transpose(1, 2)
        v = v.view(B, N, heads, d).transpose(1, 2)
        if attn.norm_q is not None:
            q = attn.norm_q(q)
        if attn.norm_k is not None:
            k = attn.norm_k(k)

        # keys/values of the K views of a group, concatenated along tokens: [G, h, K*N, d]
        k = k.reshape(G, K, heads, N, d).permute(0, 2, 1, 3, 4).reshape(G, heads, K * N, d)
        v = v.reshape(G, K, heads, N, d).permute(0, 2, 1, 3, 4).reshape(G, heads, K * N, d)
        q = q.reshape(G, K, heads, N, d)
        step = K if self.views_per_call is None else min(self.views_per_call, K)
        outs = []
        for s in range(0, K, step):
            c = min(step, K - s)
            qs = q[:, s:s + c].permute(0, 2, 1, 3, 4).reshape(G, heads, c * N, d)
            # same call (default scale 1/sqrt(d)) as diffusers' AttnProcessor2_0, so K = 1 is plain self-attention
            o = F.scaled_dot_product_attention(qs, k, v, dropout_p=0.0, is_causal=False)
            outs.append(o.reshape(G, heads, c, N, d).permute(0, 2, 1, 3, 4))
        out = torch.cat(outs, dim=1).reshape(B, heads, N, d)
        hidden_states = out.transpose(1, 2).reshape(B, N, heads * d).to(q.dtype)

        hidden_states = attn.to_out[0](hidden_states)
        hidden_states = attn.to_out[1](hidden_states)
        if input_ndim == 4:
            hidden_states = hidden_states.transpose(-1, -2).reshape(b4, c4, h4, w4)
        if attn.residual_connection:
            hidden_states = hidden_states + residual
        return hidden_states / attn.rescale_output_factor


def _attn1_names(unet) -> list[str]:
    return [n for n in unet.attn_processors if n.endswith(".attn1.processor")]


def resolve_blocks(unet, blocks: Sequence[str]) -> list[str]:
    """Block prefixes with ``"last"`` replaced by the last up-sampling block (``up_blocks.3`` on SD1.5).

    A prefix is any module path of the UNet (``up_blocks.3``, ``mid_block``,
    ``up_blocks.2.attentions.1``...). Raises InputError when a prefix holds no
    ``attn1`` layer, naming the blocks that do.
    """
    if isinstance(blocks, str):
        blocks = [blocks]
    names = _attn1_names(unet)
    out = []
    for b in blocks:
        b = str(b).strip().rstrip(".")
        if b == "last":
            b = f"up_blocks.{len(unet.up_blocks) - 1}"
        if not any(n.startswith(b + ".") for n in names):
            have = sorted({".".join(n.split(".")[:2]) if n.startswith(("up_blocks", "down_blocks"))
                           else n.split(".")[0] for n in names})
            raise InputError(f"CVSA block '{b}' has no self-attention (attn1) layer; blocks with attn1 layers: "
                             f"{', '.join(have)} (or 'last')")
        out.append(b)
    return out


def install_cvsa(unet, num_views: int, blocks: Sequence[str] = ("last",), views_per_call: Optional[int] = None
                 ) -> list[str]:
    """Put :class:`CVSAProcessor` on the ``attn1`` layers under ``blocks``; returns their processor names.

    ``blocks`` default ``("last",)`` = the last up-sampling block (``up_blocks.3``
    on SD1.5). Other processors are handed back to ``set_attn_processor``
    unchanged (same objects). Installing again replaces the CVSA settings
    (the original processors stay remembered).
    """
    prefixes = resolve_blocks(unet, blocks)
    procs = dict(unet.attn_processors)
    chosen = []
    for name, proc in procs.items():
        if name.endswith(".attn1.processor") and any(name.startswith(p + ".") for p in prefixes):
            base = proc.base if isinstance(proc, CVSAProcessor) else proc
            procs[name] = CVSAProcessor(num_views, views_per_call, base)
            chosen.append(name)
    unet.set_attn_processor(procs)
    return chosen


def remove_cvsa(unet) -> int:
    """Restore the processors CVSA replaced; returns how many were restored."""
    procs = dict(unet.attn_processors)
    n = 0
    for name, proc in procs.items():
        if isinstance(proc, CVSAProcessor):
            if proc.base is None:
                from diffusers.models.attention_processor import AttnProcessor2_0
                procs[name] = AttnProcessor2_0()
            else:
                procs[name] = proc.base
            n += 1
    if n:
        unet.set_attn_processor(procs)
    return n


def cvsa_names(unet) -> list[str]:
    """Processor names that currently carry CVSA."""
    return [n for n, p in unet.attn_processors.items() if isinstance(p, CVSAProcessor)]


@contextlib.contextmanager
def cvsa_enabled(unet, num_views: int, blocks: Sequence[str] = ("last",), views_per_call: Optional[int] = None,
                 enabled: bool = True) -> Iterator[list[str]]:
    """Context manager: CVSA installed inside, the previous processors restored on exit (errors included)."""
    if not enabled:
        yield []
        return
    names = install_cvsa(unet, num_views, blocks, views_per_call)
    try:
        yield names
    finally:
        remove_cvsa(unet)
