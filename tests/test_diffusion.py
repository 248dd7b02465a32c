"""Stage 1 (ssgwarp.stylization.diffusion) on tiny randomly initialised SD-style models: no weights, no network."""
from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("transformers")

from ssgwarp.core.cameras import Cameras, intrinsics, look_at  # noqa: E402
from fakeweights import random_stage1_components, save_stage1  # noqa: E402
from ssgwarp.stylization.diffusion import ddim_denoise, ddim_invert, ddim_step, depth_to_control, encode_latents, schedule, stylize_keyviews, stylize_views
from ssgwarp.stylization.diffusion_models import Stage1Config, assemble_stage1, load_stage1, set_ip_adapter_scales
from ssgwarp.core.imaging import save_sheet
from ssgwarp.errors import InputError, WeightsNotFound  # noqa: E402
from ssgwarp.stylization.keyviews import KeyViews  # noqa: E402
from ssgwarp.procedural import smooth_views  # noqa: E402

WEIGHT_ENV = ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
              "SSGWARP_IMAGE_ENCODER")


@pytest.fixture(autouse=True)
def offline(monkeypatch):
    for k in WEIGHT_ENV:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")


@pytest.fixture(scope="module")
def models():
    return assemble_stage1(random_stage1_components("tiny", seed=0), "cpu")


def keyviews_of(rgb, depth) -> KeyViews:
    K, H, W, _ = rgb.shape
    eyes = torch.tensor([[3.0, 0.0, 0.0]]).repeat(K, 1) + torch.arange(K).view(K, 1) * 0.1
    cams = Cameras(look_at(eyes, torch.zeros(K, 3)).float(), intrinsics(40, 40, W / 2, H / 2, K), W, H)
    return KeyViews(rgb, depth, torch.ones_like(depth), None, list(range(K)), cams, (W, H))


@pytest.mark.parametrize("spacing", ["leading", "trailing"])
def test_ddim_steps_match_diffusers_schedulers(spacing):
    """Every denoising step (eta 0 and eta > 0 with given noise, the last one to the final alpha) equals
    diffusers' ``DDIMScheduler.step``, and every inversion step ``DDIMInverseScheduler.step``, on SD1.5's
    schedule."""
    from diffusers import DDIMInverseScheduler, DDIMScheduler

    sched = DDIMScheduler(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                          clip_sample=False, set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon",
                          timestep_spacing=spacing)
    inverse = DDIMInverseScheduler.from_config(sched.config)
    g = torch.Generator().manual_seed(0)
    for steps in (10, 25):
        ts, alphas, a_final = schedule(sched, steps)
        assert ts == [int(t) for t in sched.timesteps] and a_final == pytest.approx(float(sched.alphas_cumprod[0]))
        for i, t in enumerate(ts):
            x, eps, noise = (torch.randn(2, 4, 3, 3, generator=g) for _ in range(3))
            a_to = alphas[i + 1] if i + 1 < len(ts) else a_final
            for eta in (0.0, 0.6):
                ours = ddim_step(x, eps, alphas[i], a_to, eta, noise)
                theirs = sched.step(eps, t, x, eta=eta, variance_noise=noise).prev_sample
                torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)
        inverse.set_timesteps(steps)
        assert [int(t) for t in inverse.timesteps] == ts[::-1]
        for i in range(len(ts) - 1, -1, -1):           # the order of ddim_invert
            x, eps = torch.randn(2, 4, 3, 3, generator=g), torch.randn(2, 4, 3, 3, generator=g)
            a_from = a_final if i == len(ts) - 1 else alphas[i + 1]
            torch.testing.assert_close(ddim_step(x, eps, a_from, alphas[i]), inverse.step(eps, ts[i], x).prev_sample,
                                       rtol=1e-5, atol=1e-5)


@pytest.mark.slow  # 60 DDIM steps each way through the tiny UNet
def test_inversion_reconstruction_error_falls_with_steps(models):
    """DDIM inversion then DDIM denoising (guidance 0, ControlNet on) reconstructs the latents."""
    from diffusers import DDIMScheduler

    rgb, depth = smooth_views(2, 32, 32)
    lat = encode_latents(models, rgb)
    control = depth_to_control(depth)
    text = models.encode_prompt([""]).expand(2, -1, -1)
    img = torch.zeros(2, models.image_encoder.config.projection_dim)
    # trailing spacing: every step count starts from t = 999, so only the step size changes
    sched = DDIMScheduler.from_config(models.scheduler.config, timestep_spacing="trailing")
    errors = {}
    for steps in (4, 8, 16, 32):
        s = schedule(sched, steps)
        xt = ddim_invert(models, lat, s, text, img, control)
        x0 = ddim_denoise(models, xt, s, text, text, img, img, control, guidance=0.0)
        errors[steps] = float((x0 - lat).abs().mean() / lat.abs().mean())
        assert float((xt - lat).std()) > 0.5  # the inversion really went to noise
    print("inversion-reconstruction relative L1 error by steps:", {k: round(v, 4) for k, v in errors.items()})
    vals = [errors[s] for s in (4, 8, 16, 32)]
    assert all(b < a for a, b in zip(vals, vals[1:])), errors
    assert vals[-1] < 0.5 * vals[0]


def test_stage1_end_to_end_tiny(models):
    K, H, W = 3, 40, 64   # latents 5x8: an odd latent height goes through the UNet too
    rgb, depth = smooth_views(K, H, W, seed=1)
    kv = keyviews_of(rgb, depth)
    style = torch.rand(50, 30, 3, generator=torch.Generator().manual_seed(5))
    cfg = Stage1Config(steps=3, eta=0.5, seed=7, prompt="an oil painting", progress=False)
    out = stylize_keyviews(kv, style, cfg, "cpu", models=models)
    assert out.shape == (K, H, W, 3) and out.dtype == torch.float32
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    again = stylize_keyviews(kv, style, cfg, "cpu", models=models)
    assert torch.equal(out, again)  # same seed: identical
    other_seed = stylize_views(models, rgb, depth, style, Stage1Config(steps=3, eta=0.5, seed=8, progress=False,
                                                                       prompt="an oil painting"))
    assert (other_seed - out).abs().max() > 1e-4
    # CVSA, the style image (IP-Adapter) and the depth (ControlNet) each change the result
    no_cvsa = stylize_views(models, rgb, depth, style, Stage1Config(steps=3, eta=0.5, seed=7, cvsa=False,
                                                                    prompt="an oil painting", progress=False))
    other_style = stylize_views(models, rgb, depth, style.flip(0) * 0.5, cfg)
    other_depth = stylize_views(models, rgb, depth.flip(-1), style, cfg)
    for o in (no_cvsa, other_style, other_depth):
        assert (o - out).abs().max() > 1e-5
    # per-block IP-Adapter scale 0 everywhere = IP-Adapter off: the style image no longer matters
    off = Stage1Config(steps=2, seed=7, progress=False, ip_adapter_scale=0.0)
    a = stylize_views(models, rgb, depth, style, off)
    b = stylize_views(models, rgb, depth, style.flip(0) * 0.5, off)
    torch.testing.assert_close(a, b)
    with pytest.raises(InputError, match="multiples of 8"):
        stylize_views(models, rgb[:, :36], depth[:, :36], style, cfg)


def test_ip_adapter_block_scales(models):
    scales = set_ip_adapter_scales(models.unet, 0.0, {"up_blocks.1": 1.0, "up_blocks.1.attentions.1": 0.5})
    assert scales["up_blocks.1.attentions.0.transformer_blocks.0.attn2.processor"] == 1.0
    assert scales["up_blocks.1.attentions.1.transformer_blocks.0.attn2.processor"] == 0.5
    assert scales["down_blocks.0.attentions.0.transformer_blocks.0.attn2.processor"] == 0.0
    assert models.unet.attn_processors["up_blocks.1.attentions.1.transformer_blocks.0.attn2.processor"].scale == [0.5]
    with pytest.raises(InputError, match="no IP-Adapter layer"):
        set_ip_adapter_scales(models.unet, 1.0, {"up_blocks.9": 1.0})
    set_ip_adapter_scales(models.unet, 1.0)


def test_depth_to_control():
    depth = torch.tensor([[[1.0, 2.0], [4.0, 0.0]]])
    alpha = torch.tensor([[[1.0, 1.0], [0.2, 1.0]]])
    c = depth_to_control(depth, alpha)
    assert c.shape == (1, 3, 2, 2)
    # valid: 1 and 2 (4 has low alpha, 0 has no depth): disparity 1 -> 1 (near), 0.5 -> 0 (far)
    torch.testing.assert_close(c[0, 0], torch.tensor([[1.0, 0.0], [0.0, 0.0]]))
    # normalised per view: scaling depth changes nothing
    d2 = torch.rand(2, 5, 6, generator=torch.Generator().manual_seed(2)) + 0.5
    torch.testing.assert_close(depth_to_control(d2 * 10), depth_to_control(d2))


def test_load_stage1_from_local_folders(tmp_path, models, monkeypatch):
    saved = save_stage1(random_stage1_components("tiny", seed=0), tmp_path)
    cfg = Stage1Config(**{k: str(v) for k, v in saved.items()}, steps=2, progress=False)
    loaded = load_stage1(cfg, "cpu")
    assert loaded.dtype == torch.float32 and loaded.has_ip_adapter
    ip = [n for n, p in loaded.unet.attn_processors.items() if type(p).__name__ == "IPAdapterAttnProcessor2_0"]
    assert len(ip) == 7
    rgb, depth = smooth_views(2, 32, 32, seed=2)
    style = torch.rand(20, 20, 3, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(stylize_views(loaded, rgb, depth, style, cfg),
                               stylize_views(models, rgb, depth, style, cfg), atol=1e-5, rtol=1e-5)
    # the same folders found through the environment variables
    from ssgwarp.stylization.diffusion_models import missing_weights
    assert len(missing_weights(Stage1Config())) == 4
    for key, env in [("sd15", "SSGWARP_SD15"), ("controlnet_depth", "SSGWARP_CONTROLNET_DEPTH"),
                     ("ip_adapter", "SSGWARP_IP_ADAPTER"), ("image_encoder", "SSGWARP_IMAGE_ENCODER")]:
        monkeypatch.setenv(env, str(saved[key]))
    assert missing_weights(Stage1Config()) == []
    assert Stage1Config().torch_dtype("cpu") == torch.float32
    assert Stage1Config().torch_dtype("cuda") == torch.float16


def test_missing_weights_message(tmp_path, capsys, monkeypatch):
    rgb, depth = smooth_views(1, 16, 16)
    kv = keyviews_of(rgb, depth)
    cfg = Stage1Config(progress=False)
    assert stylize_keyviews(kv, torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(0)), cfg, "cpu") is None
    err = capsys.readouterr().err
    assert "Stage 1 skipped" in err and "Stage 2 will match against the style image itself" in err
    for key in ("sd15", "controlnet_depth", "ip_adapter", "image_encoder"):   # short: each model and its fetch
        assert f"ssgwarp weights --download {key}" in err, key
    from ssgwarp.services import weights as W

    with W.verbose():           # --debug: the long form, where each is looked for
        stylize_keyviews(kv, torch.rand(8, 8, 3, generator=torch.Generator().manual_seed(0)), cfg, "cpu")
    err = capsys.readouterr().err
    for text in ("stable-diffusion-v1-5/stable-diffusion-v1-5", "lllyasviel/control_v11f1p_sd15_depth",
                 "h94/IP-Adapter", "ip-adapter_sd15.safetensors", "SSGWARP_SD15", "model_index.json"):
        assert text in err, text
    # a half-present SD folder: the message names the files that are missing
    (tmp_path / "sd15" / "vae").mkdir(parents=True)
    (tmp_path / "sd15" / "vae" / "config.json").write_text("{}")
    with pytest.raises(WeightsNotFound, match="unet/config.json"):
        load_stage1(Stage1Config(sd15=str(tmp_path / "sd15")), "cpu")
    monkeypatch.setenv("SSGWARP_WEIGHTS", str(tmp_path / "nowhere"))
    with pytest.raises(WeightsNotFound, match="controlnet_depth"):
        load_stage1(Stage1Config(), "cpu")


def test_save_sheet(tmp_path):
    from ssgwarp.core.fileio import read_image

    a = torch.zeros(3, 16, 24, 3)
    b = torch.ones(3, 16, 24, 3) * 0.5
    p = save_sheet(a, b, tmp_path / "sheet.png", gap=4)
    img = read_image(p)
    assert img.shape == (3 * 16 + 2 * 4, 2 * 24 + 4, 3)
    assert abs(float(img[0, 30, 0]) - 0.5) < 0.01 and float(img[0, 0, 0]) == 0.0


def test_config_validation():
    with pytest.raises(InputError):
        Stage1Config(steps=0).validate()
    with pytest.raises(InputError):
        Stage1Config(strength=1.5).validate()
    with pytest.raises(InputError):
        Stage1Config(dtype="fp8").validate()
    assert math.isclose(Stage1Config(strength=0.5).validate().strength, 0.5)
