"""SSIM, PSNR and LPIPS against values computed independently in the test (closed forms, numpy,
the LPIPS definition written out with ``F.conv2d`` on the raw weights) — never a value against
itself."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ssgwarp.evaluation import metrics as M
from ssgwarp.evaluation import networks as N
from ssgwarp.services.losses import psnr, ssim

C1, C2 = 0.01 ** 2, 0.03 ** 2       # SSIM's stabilisers for images in [0, 1] (K1 = 0.01, K2 = 0.03)


def ssim_numpy(a: np.ndarray, b: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM of ``[H, W, C]`` images: Gaussian window (sigma 1.5) applied separably with reflect
    padding (the convention ``ssgwarp.services.losses.ssim`` documents), local means, variances and covariance,
    ``(2 mu_a mu_b + C1)(2 s_ab + C2) / ((mu_a^2 + mu_b^2 + C1)(s_a^2 + s_b^2 + C2))``."""
    r = window // 2
    k = np.exp(-((np.arange(window) - r) ** 2) / (2 * sigma ** 2))
    k /= k.sum()

    def blur(x):
        x = np.pad(x, ((r, r), (r, r), (0, 0)), mode="reflect")
        x = np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), 0, x)
        return np.apply_along_axis(lambda v: np.convolve(v, k, mode="valid"), 1, x)

    ma, mb = blur(a), blur(b)
    va, vb, cab = blur(a * a) - ma ** 2, blur(b * b) - mb ** 2, blur(a * b) - ma * mb
    s = (2 * ma * mb + C1) * (2 * cab + C2) / ((ma ** 2 + mb ** 2 + C1) * (va + vb + C2))
    return float(s.mean())


def test_ssim_of_constant_images_has_the_closed_form():
    """Constant images (no variance): SSIM = (2ab + C1) / (a^2 + b^2 + C1) per channel, averaged."""
    a = np.array([0.2, 0.5, 0.9])
    b = np.array([0.4, 0.5, 0.3])
    A = torch.tensor(a, dtype=torch.float64).expand(1, 16, 20, 3).clone()
    B = torch.tensor(b, dtype=torch.float64).expand(1, 16, 20, 3).clone()
    expect = float(np.mean((2 * a * b + C1) / (a * a + b * b + C1)))
    assert expect < 0.85
    assert float(ssim(A, B)) == pytest.approx(expect, abs=1e-7)


def test_ssim_of_a_textured_pair_matches_an_independent_computation():
    g = np.random.default_rng(3)
    a = g.random((20, 24, 3))
    b = np.clip(0.7 * a + 0.2 * g.random((20, 24, 3)) + 0.05, 0, 1)
    expect = ssim_numpy(a, b)
    assert 0.3 < expect < 0.95
    got = float(ssim(torch.from_numpy(a)[None], torch.from_numpy(b)[None]))
    assert got == pytest.approx(expect, abs=1e-8)
    # [H, W, C] input is the same as a batch of one
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(b))) == pytest.approx(expect, abs=1e-8)


def test_psnr_of_a_known_error():
    a = torch.full((1, 8, 8, 3), 0.4, dtype=torch.float64)   # not zero: a sum a + b would differ from a - b
    b = a.clone()
    b[..., 0] = 0.7                           # MSE = 0.09 / 3 = 0.03
    assert float(psnr(a, b)) == pytest.approx(-10 * math.log10(0.03), abs=1e-9)
    assert float(psnr(b, a)) == pytest.approx(-10 * math.log10(0.03), abs=1e-9)
    # equal images: the MSE floor 1e-20 gives 200 dB, not inf
    assert float(psnr(a, a)) == pytest.approx(200.0, abs=1e-9)


def _vgg_features(state, x, upto):
    """VGG16 relu1_2 (and relu2_2) written out on the raw torchvision-layout weights."""
    h = F.relu(F.conv2d(x, state["features.0.weight"], state["features.0.bias"], padding=1))
    h = F.relu(F.conv2d(h, state["features.2.weight"], state["features.2.bias"], padding=1))
    out = [h]
    if upto > 1:
        h = F.max_pool2d(h, 2)
        h = F.relu(F.conv2d(h, state["features.5.weight"], state["features.5.bias"], padding=1))
        h = F.relu(F.conv2d(h, state["features.7.weight"], state["features.7.bias"], padding=1))
        out.append(h)
    return out


def test_lpips_value_follows_its_definition(tmp_path):
    """LPIPS with heads on relu1_2 and relu2_2 only: inputs mapped to [-1, 1], shifted by
    (-0.030, -0.088, -0.188) and scaled by (0.458, 0.448, 0.450); features unit-normalised along
    channels; squared difference weighted per channel by the head, averaged over space, summed."""
    torch.manual_seed(0)
    vgg = {f"features.{k}": v for k, v in N.LPIPS().trunk.features.state_dict().items()}
    g = torch.Generator().manual_seed(1)
    w0, w1 = torch.rand(1, 64, 1, 1, generator=g), torch.rand(1, 128, 1, 1, generator=g)
    lins = {"lin0.model.1.weight": w0, "lin1.model.1.weight": w1}
    lins.update({f"lin{i}.model.1.weight": torch.zeros(1, c, 1, 1) for i, c in enumerate(N.LPIPS_CHANNELS) if i > 1})
    torch.save(vgg, tmp_path / "vgg16.pth")
    torch.save(lins, tmp_path / "lpips_vgg.pth")
    lp = N.load_lpips(tmp_path / "lpips_vgg.pth", tmp_path / "vgg16.pth")
    x = torch.rand(2, 3, 24, 20, generator=g)
    y = (x + 0.2 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)
    fx = _vgg_features(vgg, (2 * x - 1 - shift) / scale, 2)
    fy = _vgg_features(vgg, (2 * y - 1 - shift) / scale, 2)
    expect = torch.zeros(2)
    for a, b, w in zip(fx, fy, (w0, w1)):
        a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        expect += (w * (a - b) ** 2).sum(1).mean(dim=(1, 2))
    with torch.no_grad():
        got = lp(x, y)
    assert (expect > 1e-3).all()
    torch.testing.assert_close(got, expect, rtol=1e-5, atol=1e-7)
    # the distance grows with the perturbation
    with torch.no_grad():
        assert (lp(x, (x + 0.05 * (y - x))) < got).all()
