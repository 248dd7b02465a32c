"""Cross-View Style Alignment processors (ssgwarp.stylization.cvsa) on a tiny random UNet with IP-Adapter."""
from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("diffusers")

from fakeweights import random_stage1_components  # noqa: E402
from ssgwarp.stylization.cvsa import CVSAProcessor, cvsa_enabled, cvsa_names, install_cvsa, remove_cvsa  # noqa: E402
from ssgwarp.stylization.diffusion_models import assemble_stage1  # noqa: E402
from ssgwarp.errors import InputError  # noqa: E402


@pytest.fixture(scope="module")
def models():
    return assemble_stage1(random_stage1_components("tiny", seed=0), "cpu")


def _attn1(unet, name="up_blocks.1.attentions.0.transformer_blocks.0.attn1"):
    return unet.get_submodule(name)


def reference_cvsa(attn, x: torch.Tensor, K: int) -> torch.Tensor:
    """Hand-written CVSA: per group of K views, per head, softmax(q k_cat^T / sqrt(d)) v_cat."""
    B, N, _ = x.shape
    h = attn.heads
    q, k, v = attn.to_q(x), attn.to_k(x), attn.to_v(x)
    d = q.shape[-1] // h
    out = torch.empty_like(q)
    for g in range(B // K):
        views = range(g * K, (g + 1) * K)
        kc = torch.cat([k[j] for j in views], 0)   # [K*N, h*d]
        vc = torch.cat([v[j] for j in views], 0)
        for i in views:
            for hh in range(h):
                sl = slice(hh * d, (hh + 1) * d)
                s = q[i, :, sl] @ kc[:, sl].T / math.sqrt(d)
                out[i, :, sl] = torch.softmax(s, dim=-1) @ vc[:, sl]
    return attn.to_out[1](attn.to_out[0](out))


def test_processor_map_cvsa_only_on_chosen_attn1(models):
    unet = models.unet
    before = dict(unet.attn_processors)
    ip_types = {n: type(p).__name__ for n, p in before.items() if n.endswith("attn2.processor")}
    assert set(ip_types.values()) == {"IPAdapterAttnProcessor2_0"}
    names = install_cvsa(unet, num_views=3)  # default: the last up-sampling block
    try:
        after = unet.attn_processors
        expect = sorted(n for n in before if n.startswith("up_blocks.1.") and n.endswith("attn1.processor"))
        assert sorted(names) == expect == sorted(cvsa_names(unet)) and len(expect) == 2
        for n, p in after.items():
            if n in expect:
                assert isinstance(p, CVSAProcessor) and p.num_views == 3 and p.base is before[n]
            else:
                assert p is before[n], n  # the same object: IP-Adapter processors and weights untouched
        # several blocks, including the mid block; reinstalling keeps the original bases
        names2 = install_cvsa(unet, 2, blocks=("up_blocks.0", "mid_block", "up_blocks.1"))
        assert len(names2) == 5
        assert all(unet.attn_processors[n].base is before[n] for n in names2)
    finally:
        assert remove_cvsa(unet) >= 2
    assert all(p is before[n] for n, p in unet.attn_processors.items())
    with pytest.raises(InputError, match="no self-attention"):
        install_cvsa(unet, 2, blocks=("up_blocks.7",))


@pytest.mark.parametrize("views_per_call", [None, 1, 2])
def test_cvsa_equals_reference_over_concatenated_keys(models, views_per_call):
    attn = _attn1(models.unet)
    base = attn.processor
    K, G, N = 3, 2, 10
    x = torch.randn(G * K, N, attn.to_q.in_features, generator=torch.Generator().manual_seed(1))
    try:
        attn.set_processor(CVSAProcessor(K, views_per_call))
        with torch.no_grad():
            got = attn(x)
            ref = reference_cvsa(attn, x, K)
    finally:
        attn.set_processor(base)
    torch.testing.assert_close(got, ref, atol=2e-5, rtol=1e-4)


def test_one_view_is_plain_self_attention(models):
    attn = _attn1(models.unet)
    x = torch.randn(4, 12, attn.to_q.in_features, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        plain = attn(x)
        base = attn.processor
        attn.set_processor(CVSAProcessor(1))
        try:
            one = attn(x)
        finally:
            attn.set_processor(base)
    torch.testing.assert_close(one, plain, atol=1e-6, rtol=1e-5)
    # and the whole UNet (ControlNet residuals aside) with CVSA for one view equals the UNet without it
    unet = models.unet
    g = torch.Generator().manual_seed(3)
    lat = torch.randn(2, 4, 6, 8, generator=g)
    text = torch.randn(2, 77, 32, generator=g)
    img = [torch.randn(2, 1, 16, generator=g)]
    with torch.no_grad():
        ref = unet(lat, 500, text, added_cond_kwargs={"image_embeds": img}).sample
        with cvsa_enabled(unet, 1, blocks=("up_blocks.0", "up_blocks.1", "mid_block", "down_blocks.0")):
            got = unet(lat, 500, text, added_cond_kwargs={"image_embeds": img}).sample
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-4)


def test_cfg_halves_do_not_mix_and_views_do(models):
    attn = _attn1(models.unet)
    K, N = 2, 8
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2 * K, N, attn.to_q.in_features, generator=g)  # [uncond v0, uncond v1, cond v0, cond v1]
    base = attn.processor
    attn.set_processor(CVSAProcessor(K))
    try:
        with torch.no_grad():
            out = attn(x)
            y = x.clone()
            y[K:] += torch.randn(K, N, x.shape[-1], generator=g)  # change the conditional half only
            out_y = attn(y)
            z = x.clone()
            z[1] += torch.randn(N, x.shape[-1], generator=g)  # change unconditional view 1 only
            out_z = attn(z)
    finally:
        attn.set_processor(base)
    torch.testing.assert_close(out_y[:K], out[:K])             # unconditional half untouched
    assert (out_z[0] - out[0]).abs().max() > 1e-3               # view 0 sees view 1 (cross-view)
    torch.testing.assert_close(out_z[K:], out[K:])             # the conditional half does not
    # identical views: attention over K duplicated key sets equals plain self-attention
    dup = x[:1].expand(K, -1, -1).contiguous()
    with torch.no_grad():
        plain = attn(dup)
        attn.set_processor(CVSAProcessor(K))
        try:
            shared = attn(dup)
        finally:
            attn.set_processor(base)
    torch.testing.assert_close(shared, plain, atol=1e-6, rtol=1e-5)


def test_batch_must_hold_whole_groups(models):
    attn = _attn1(models.unet)
    base = attn.processor
    attn.set_processor(CVSAProcessor(3))
    try:
        with pytest.raises(ValueError, match="multiple of num_views"):
            attn(torch.randn(4, 5, attn.to_q.in_features, generator=torch.Generator().manual_seed(6)))
    finally:
        attn.set_processor(base)
    with pytest.raises(InputError):
        CVSAProcessor(0)


def test_guided_denoising_shares_attention_within_each_cfg_half_only(models):
    """Stage 1's denoising step with guidance and CVSA equals the step computed from each CFG half
    alone (CVSA over the K unconditional views, and over the K conditional views); attention across
    both halves (one group of 2K views) gives a step 20x further away than the tolerance, so a CVSA
    that mixes the halves cannot pass. One trailing step from t = 999 amplifies the noise estimate
    (x0 = (x - sqrt(1 - a) eps) / sqrt(a), a = 0.005)."""
    from diffusers import DDIMScheduler

    from ssgwarp.stylization.diffusion import ddim_denoise, ddim_step, predict_noise, schedule

    K, w, blocks = 2, 3.0, ("mid_block", "up_blocks.0", "up_blocks.1")
    g = torch.Generator().manual_seed(5)
    x = torch.randn(K, 4, 8, 8, generator=g)
    control = torch.rand(K, 3, 8 * models.vae_scale_factor, 8 * models.vae_scale_factor, generator=g)
    text_u = models.encode_prompt(["", ""])
    text_c = models.encode_prompt(["a painting", "a painting"])
    dim = models.image_encoder.config.projection_dim
    img_u, img_c = torch.zeros(K, dim), torch.randn(K, dim, generator=g)
    sched = schedule(DDIMScheduler.from_config(models.scheduler.config, timestep_spacing="trailing"), 1)
    ts, alphas, a_final = sched
    assert ts == [999]
    got = ddim_denoise(models, x, sched, text_u, text_c, img_u, img_c, control, guidance=w, cvsa=True,
                       cvsa_blocks=blocks)
    with cvsa_enabled(models.unet, K, blocks):
        eu = predict_noise(models, x, ts[0], text_u, img_u, control)
        ec = predict_noise(models, x, ts[0], text_c, img_c, control)
    expect = ddim_step(x, eu + w * (ec - eu), alphas[0], a_final)
    torch.testing.assert_close(got, expect, atol=5e-4, rtol=0)
    with cvsa_enabled(models.unet, 2 * K, blocks):                  # the fault: one group of 2K views
        mu, mc = predict_noise(models, torch.cat([x, x]), ts[0], torch.cat([text_u, text_c]),
                               torch.cat([img_u, img_c]), torch.cat([control, control])).chunk(2)
    mixed = ddim_step(x, mu + w * (mc - mu), alphas[0], a_final)
    assert (mixed - expect).abs().max() > 20 * 5e-4
