"""Feature extractors: VGG16 torchvision layout, random extractor determinism, Gram loss."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from ssgwarp.errors import InputError, WeightsNotFound
from ssgwarp.evaluation.features import (VGG16_LAYERS, RandomMultiScale, gram_loss, gram_matrix,
                              load_extractor, resolve_layers, stack_features)


def _torchvision_like_state(seed: int = 0) -> dict:
    """A random VGG16 state dict with torchvision's key names (features.* and classifier.*)."""
    g = torch.Generator().manual_seed(seed)
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
    state, idx, cin = {}, 0, 3
    for v in cfg:
        if v == "M":
            idx += 1
            continue
        state[f"features.{idx}.weight"] = torch.randn(v, cin, 3, 3, generator=g) * 0.05
        state[f"features.{idx}.bias"] = torch.randn(v, generator=g) * 0.01
        idx += 2
        cin = v
    state["classifier.0.weight"] = torch.zeros(4, 4)  # ignored, as torchvision files carry it
    return state


def test_vgg_layer_names_follow_torchvision_indices():
    assert len(VGG16_LAYERS) == 31
    assert VGG16_LAYERS[0] == "conv1_1" and VGG16_LAYERS[4] == "pool1"
    assert VGG16_LAYERS[11] == "relu3_1" and VGG16_LAYERS[15] == "relu3_3" and VGG16_LAYERS[30] == "pool5"
    assert resolve_layers(None) == [11, 13, 15]
    assert resolve_layers(["relu1_2", 8, "conv4"]) == [3, 8, 18, 20, 22]
    with pytest.raises(InputError):
        resolve_layers(["relu9_1"])


def test_vgg16_loads_torchvision_state_dict_and_matches_manual_forward(tmp_path):
    state = _torchvision_like_state()
    path = tmp_path / "vgg16-test.pth"
    torch.save(state, path)
    ext = load_extractor(path, layers=["relu1_2", "relu2_1"])
    assert ext.name == "vgg16:relu1_2+relu2_1" and ext.strides == [1, 2]
    x = torch.rand(1, 3, 20, 24, generator=torch.Generator().manual_seed(0))
    f12, f21 = ext(x)
    # the same network written out with F.conv2d on the raw state dict
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    h = (x - mean) / std
    h = F.relu(F.conv2d(h, state["features.0.weight"], state["features.0.bias"], padding=1))
    h = F.relu(F.conv2d(h, state["features.2.weight"], state["features.2.bias"], padding=1))
    torch.testing.assert_close(f12, h)
    h = F.max_pool2d(h, 2)
    h = F.relu(F.conv2d(h, state["features.5.weight"], state["features.5.bias"], padding=1))
    torch.testing.assert_close(f21, h)
    assert all(not p.requires_grad for p in ext.parameters())


def test_vgg16_rejects_wrong_state_dict(tmp_path):
    bad = {"features.0.weight": torch.zeros(64, 3, 3, 3)}  # incomplete
    path = tmp_path / "bad.pth"
    torch.save(bad, path)
    with pytest.raises(InputError, match="lacks"):
        load_extractor(path)
    with pytest.raises(InputError):
        load_extractor(tmp_path / "missing.pth")


def test_default_is_random_when_no_weights(monkeypatch):
    monkeypatch.delenv("SSGWARP_VGG16", raising=False)
    monkeypatch.delenv("SSGWARP_WEIGHTS", raising=False)
    ext = load_extractor()
    assert ext.name == "random-multiscale:seed0,c128s2"
    # ssgwarp stylize's weight-free default: the edge features
    assert load_extractor(fallback="random-edges").name == "random-multiscale:seed0,c128s2p2-4-8,edges"
    assert load_extractor(kind="random", fallback="random-edges").name == "random-multiscale:seed0,c128s2"
    with pytest.raises(InputError, match="fallback"):
        load_extractor(fallback="vgg16")
    with pytest.raises(WeightsNotFound):
        load_extractor(kind="vgg16")


def test_random_extractor_deterministic_for_seed_and_differentiable():
    x = torch.rand(2, 3, 36, 44, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    a, b, c = RandomMultiScale(seed=3), RandomMultiScale(seed=3), RandomMultiScale(seed=4)
    fa, fb, fc = a(x), b(x), c(x)
    assert [f.shape for f in fa] == [torch.Size([2, 128, 18, 22])] * 3
    legacy = RandomMultiScale(seed=3, channels=64, stride=4)       # the extractor of earlier versions
    assert legacy.name == "random-multiscale:seed3"
    assert [f.shape for f in legacy(x)] == [torch.Size([2, 64, 9, 11])] * 3
    for u, v in zip(fa, fb):
        assert torch.equal(u, v)
    assert not torch.allclose(fa[0], fc[0])
    stack_features(fa).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_edges_extractor_sees_edges_not_colour():
    """``edges=True`` (``--extractor random-edges``): first-layer filters with no mean over the window,
    norms kept, so every flat colour gives the same features, while an edge still responds."""
    from ssgwarp.evaluation.features import zero_mean_filters

    w = torch.randn(8, 3, 3, 3, generator=torch.Generator().manual_seed(0))
    z = zero_mean_filters(w)
    torch.testing.assert_close(z.mean(dim=(2, 3)), torch.zeros(8, 3), atol=1e-6, rtol=0)
    torch.testing.assert_close(z.flatten(1).norm(dim=1), w.flatten(1).norm(dim=1))
    plain, edges = RandomMultiScale(seed=0), RandomMultiScale(seed=0, edges=True)
    assert edges.name == "random-multiscale:seed0,c128s2,edges" and plain.name == "random-multiscale:seed0,c128s2"
    coarse = load_extractor(kind="random-edges")      # the CLI's option: branches at 1/2, 1/4, 1/8
    assert coarse.name == "random-multiscale:seed0,c128s2p2-4-8,edges" and coarse.scales == (2, 4, 8)
    assert [b[0].weight.mean(dim=(2, 3)).abs().max() < 1e-6 for b in coarse.branches] == [True] * 3
    red, blue = torch.zeros(1, 3, 32, 32), torch.zeros(1, 3, 32, 32)
    red[:, 0], blue[:, 2] = 0.9, 0.6
    for a, b in zip(edges(red), edges(blue)):        # two flat colours: the same features
        torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    assert not torch.allclose(plain(red)[0], plain(blue)[0], atol=1e-3)   # the plain extractor sees colour
    step = red.clone()
    step[..., 16:] = blue[..., 16:]
    f = edges(step)[0]
    assert (f[..., 8] - f[..., 2]).abs().max() > 0.05    # the edge (feature column 8 = pixel 16) responds
    with pytest.raises(InputError, match="random-edges"):
        load_extractor(kind="edges")


def test_gram_loss_hand_computed():
    f = torch.tensor([[[[1.0, 2.0], [0.0, 1.0]], [[0.0, 1.0], [1.0, 1.0]]]])  # [1,2,2,2]
    g = gram_matrix(f)
    # rows: c0 = [1,2,0,1], c1 = [0,1,1,1]; divided by h*w = 4
    torch.testing.assert_close(g[0], torch.tensor([[6.0, 3.0], [3.0, 3.0]]) / 4)
    ext = RandomMultiScale(seed=0)
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 3, 32, 32, generator=g)
    assert gram_loss(ext, x, x).item() == 0.0
    assert gram_loss(ext, x, torch.rand(1, 3, 40, 28, generator=g)).item() > 0.0
