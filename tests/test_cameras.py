"""ssgwarp.core.cameras: the OpenCV convention of ``look_at`` against hand-derived matrices, intrinsics,
selection, device/dtype moves, rescaling, the cameras.json round trip and the validation errors."""
from __future__ import annotations

import json

import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError


def _cams(n=3, w=40, h=30):
    eyes = torch.tensor([[0.0, 0.0, -3.0], [3.0, 0.0, 0.0], [1.0, 2.0, -2.0], [-2.0, 1.0, 1.0]])[:n]
    K = intrinsics(50.0, 52.0, 20.0, 15.0, n)
    K[:, 0, 0] += torch.arange(n)  # distinct focal lengths: shows which camera is which
    return Cameras(look_at(eyes, torch.zeros(n, 3), up=(0.0, 1.0, 0.0)).float(), K, w, h, [f"c{i}" for i in range(n)])


def test_look_at_matches_hand_derived_matrices():
    # at (0, 0, -3) looking at the origin with world up +y: z = +z, x = z x up = -x, y = z x x = -y
    V = look_at(torch.tensor([[0.0, 0.0, -3.0]]), torch.zeros(1, 3), up=(0.0, 1.0, 0.0))
    want = torch.tensor([[-1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, 1.0, 3.0], [0, 0, 0, 1.0]], dtype=torch.float64)
    assert V.dtype == torch.float64 and torch.allclose(V[0], want, atol=1e-12)
    # the default up is +z: at (3, 0, 0), z = -x, x = z x (+z) = +y, y = z x x = -z (world up is image up)
    V = look_at(torch.tensor([[3.0, 0.0, 0.0]]), torch.zeros(3))
    want = torch.tensor([[0.0, 1, 0, 0], [0, 0, -1, 0], [-1, 0, 0, 3.0], [0, 0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(V[0], want, atol=1e-12)


def test_look_at_puts_the_target_on_the_optical_axis_with_y_down():
    eyes = torch.tensor([[1.0, 2.0, -2.0], [-2.0, 1.0, 1.5], [0.5, -3.0, 0.2]], dtype=torch.float64)
    targets = torch.tensor([[0.2, 0.1, 0.0], [0.0, 0.5, -0.3], [1.0, 0.0, 0.0]], dtype=torch.float64)
    V = look_at(eyes, targets.tolist(), up=(0.0, 0.0, 1.0))  # lists of floats are taken in float64 too
    R, t = V[:, :3, :3], V[:, :3, 3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(3, dtype=torch.float64))
    assert torch.allclose(V[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64).expand(3, 4))
    # the eye maps to the camera origin, the target to (0, 0, distance)
    assert torch.allclose(torch.einsum("cij,cj->ci", R, eyes) + t, torch.zeros(3, 3, dtype=torch.float64), atol=1e-12)
    tc = torch.einsum("cij,cj->ci", R, targets) + t
    assert torch.allclose(tc[:, :2], torch.zeros(3, 2, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(tc[:, 2], (targets - eyes).norm(dim=1))
    # world up (+z) points up in the image: negative camera y
    assert bool((R[:, 1, 2] < 0).all())


def test_intrinsics():
    K = intrinsics(50.0, 52.0, 20.5, 15.5, n=2, dtype=torch.float64)
    want = torch.tensor([[50.0, 0, 20.5], [0, 52.0, 15.5], [0, 0, 1]], dtype=torch.float64)
    assert K.shape == (2, 3, 3) and K.dtype == torch.float64 and torch.equal(K, want.expand(2, 3, 3))
    assert intrinsics(1.0, 1.0, 0.0, 0.0).shape == (1, 3, 3) and intrinsics(1.0, 1.0, 0.0, 0.0).dtype == torch.float32


def test_centres_forwards_and_camtoworlds():
    cams = _cams(4)
    eyes = torch.tensor([[0.0, 0.0, -3.0], [3.0, 0.0, 0.0], [1.0, 2.0, -2.0], [-2.0, 1.0, 1.0]])
    assert torch.allclose(cams.centers, eyes, atol=1e-5)
    assert torch.allclose(cams.forwards, torch.nn.functional.normalize(-eyes, dim=1), atol=1e-6)
    assert torch.allclose(cams.camtoworlds @ cams.viewmats, torch.eye(4).expand(4, 4, 4), atol=1e-5)
    assert cams.device == torch.device("cpu") and len(cams) == 4


def test_construction_defaults_and_validation():
    V, K = _cams(2).viewmats, _cams(2).Ks
    c = Cameras(V, K, 40.0, 30.0)
    assert (c.width, c.height) == (40, 30) and type(c.width) is int and type(c.height) is int
    assert c.names == ["0000", "0001"]
    Cameras(V, K, 1, 1)  # the smallest image
    with pytest.raises(InputError, match=r"viewmats must be \[C, 4, 4\], got \(4, 4\)"):
        Cameras(V[0], K, 40, 30)
    with pytest.raises(InputError, match=r"viewmats must be \[C, 4, 4\], got \(2, 3, 4\)"):
        Cameras(V[:, :3], K, 40, 30)
    with pytest.raises(InputError, match=r"Ks must be \[C, 3, 3\] with C=2, got \(1, 3, 3\)"):
        Cameras(V, K[:1], 40, 30)
    with pytest.raises(InputError, match=r"Ks must be \[C, 3, 3\]"):
        Cameras(V, K[:, :2], 40, 30)
    for w, h in ((0, 30), (40, 0), (-1, 30)):
        with pytest.raises(InputError, match=rf"bad image size {w}x{h}"):
            Cameras(V, K, w, h)
    with pytest.raises(InputError, match="1 names for 2 cameras"):
        Cameras(V, K, 40, 30, ["a"])


@pytest.mark.parametrize("idx, want", [
    (1, [1]), (slice(1, None), [1, 2, 3]), (slice(None, None, 2), [0, 2]), ([3, 0], [3, 0]), ((2,), [2]),
    (torch.tensor([False, True, False, True]), [1, 3]), (torch.tensor([2, 1]), [2, 1]),
])
def test_selection(idx, want):
    cams = _cams(4)
    sub = cams[idx]
    assert sub.names == [f"c{i}" for i in want] and (sub.width, sub.height) == (40, 30)
    assert torch.equal(sub.viewmats, cams.viewmats[want]) and torch.equal(sub.Ks, cams.Ks[want])


def test_empty_selection():
    none = _cams(4)[torch.zeros(4, dtype=torch.bool)]  # e.g. a capture without test views
    assert len(none) == 0 and none.names == [] and none.viewmats.shape == (0, 4, 4) and none.Ks.shape == (0, 3, 3)
    assert len(_cams(4)[[]]) == 0


def test_to_changes_dtype_and_keeps_everything_else():
    cams = _cams(2)
    d = cams.to(dtype=torch.float64)
    assert d.viewmats.dtype == d.Ks.dtype == torch.float64
    assert torch.equal(d.viewmats, cams.viewmats.double()) and torch.equal(d.Ks, cams.Ks.double())
    assert d.names == cams.names and d.names is not cams.names and (d.width, d.height) == (40, 30)
    assert d.to("cpu").device == torch.device("cpu")
    # both tensors move (the meta device stands in for a GPU on a machine without one)
    m = cams.to("meta")
    assert m.viewmats.device.type == m.Ks.device.type == "meta" and m.device.type == "meta"
    assert m.viewmats.dtype == torch.float32 and m[[1]].names == ["c1"] and m[[1]].viewmats.device.type == "meta"


def test_rescaled_scales_each_row_of_K():
    cams = _cams(2)
    r = cams.rescaled(20, 45)  # x 0.5 horizontally, x 1.5 vertically
    assert (r.width, r.height) == (20, 45) and r.names == cams.names
    want = cams.Ks.clone()
    want[:, 0] *= 0.5
    want[:, 1] *= 1.5
    assert torch.equal(r.Ks, want) and torch.equal(r.Ks[:, 2], cams.Ks[:, 2])
    assert torch.equal(r.viewmats, cams.viewmats)
    r.Ks[0, 0, 0] = 0.0
    r.viewmats[0, 0, 0] = 7.0
    assert cams.Ks[0, 0, 0] == 50.0 and cams.viewmats[0, 0, 0] != 7.0  # copies, not views


def test_json_round_trip(tmp_path):
    cams = _cams(3)
    cams.save(tmp_path / "cameras.json")
    raw = json.loads((tmp_path / "cameras.json").read_text())
    assert (raw["width"], raw["height"]) == (40, 30) and [c["name"] for c in raw["cameras"]] == ["c0", "c1", "c2"]
    assert raw["convention"].startswith("opencv:") and "world-to-camera" in raw["convention"]  # says its axes
    assert raw["cameras"][1]["K"] == cams.Ks[1].double().tolist()
    assert raw["cameras"][2]["viewmat"] == cams.viewmats[2].double().tolist()
    back = Cameras.load(tmp_path / "cameras.json")
    assert back.names == cams.names and (back.width, back.height) == (40, 30)
    assert torch.equal(back.viewmats, cams.viewmats) and torch.equal(back.Ks, cams.Ks)
    assert back.viewmats.dtype == torch.float32
    b64 = Cameras.load(tmp_path / "cameras.json", dtype=torch.float64)
    assert b64.viewmats.dtype == b64.Ks.dtype == torch.float64 and torch.equal(b64.Ks, cams.Ks.double())


@pytest.mark.parametrize("damage", [
    lambda d: d.pop("cameras"), lambda d: d.pop("width"), lambda d: d["cameras"][0].pop("K"),
    lambda d: d["cameras"][1].update(viewmat=[[1.0, 2.0]]), lambda d: d.update(height="tall"),
    lambda d: d["cameras"][0].update(K=None),
])
def test_bad_cameras_file_is_one_input_error(tmp_path, damage):
    d = _cams(2).to_json()
    damage(d)
    (tmp_path / "c.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"^cameras file: unexpected layout \("):
        Cameras.load(tmp_path / "c.json")
