"""The sky behind the splats: ssgwarp.raster.environment (the field) and ssgwarp.reconstruction.sky (--sky)."""
from __future__ import annotations

import math

import pytest
import torch

from ssgwarp.errors import InputError
from ssgwarp.raster.environment import Environment, ray_directions, sample


def test_ray_directions_are_the_cameras_pixel_rays():
    from ssgwarp.procedural import rig_cameras

    cams = rig_cameras(4, 9, 7)
    d = ray_directions(cams)
    assert d.shape == (4, 7, 9, 3) and torch.allclose(d.norm(dim=-1), torch.ones(4, 7, 9), atol=1e-5)
    # the centre pixel looks along the optical axis
    assert torch.allclose(d[:, 3, 4], torch.nn.functional.normalize(cams.forwards.float(), dim=1), atol=1e-5)
    # image x to the right of the centre: the camera's right; image y down: the camera's down
    c2w = cams.camtoworlds.float()
    right = (d[:, 3, 8] - d[:, 3, 4]) @ torch.eye(3)
    assert all(float(right[i] @ c2w[i, :3, 0]) > 0 for i in range(4))
    assert all(float((d[i, 6, 4] - d[i, 3, 4]) @ c2w[i, :3, 1]) > 0 for i in range(4))


def test_sample_reads_cells_at_their_centres_and_wraps_in_azimuth():
    rows, cols = 4, 8
    grid = torch.rand(3, rows, cols, generator=torch.Generator().manual_seed(0))
    r, c = 1, 5
    el = math.radians(90 - (r + 0.5) * 180 / rows)
    az = -math.pi + (c + 0.5) * 2 * math.pi / cols
    d = torch.tensor([[math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]])
    assert torch.allclose(sample(grid, d)[0], grid[:, r, c], atol=1e-5)
    # on the seam (azimuth +-180 degrees): halfway between the last and the first column, from both sides
    el = math.radians(90 - (2 + 0.5) * 180 / rows)
    seam = torch.tensor([[-math.cos(el), 1e-7, math.sin(el)], [-math.cos(el), -1e-7, math.sin(el)]])
    want = 0.5 * (grid[:, 2, 0] + grid[:, 2, -1])
    out = sample(grid, seam)
    assert torch.allclose(out[0], want, atol=1e-4) and torch.allclose(out[1], want, atol=1e-4)


def test_an_environment_composites_behind_the_splats_and_round_trips(tmp_path):
    from ssgwarp.procedural import rig_cameras

    cams = rig_cameras(2, 6, 5)
    env = Environment.constant([0.2, 0.4, 0.8], rows=4, cols=8)
    color = torch.full((2, 5, 6, 3), 0.3)
    alpha = torch.zeros(2, 5, 6, 1)
    alpha[:, :, :3] = 1.0
    out = env.composite(color, alpha, cams)
    assert torch.allclose(out[:, :, 3:], torch.tensor([0.5, 0.7, 1.1]).expand(2, 5, 3, 3), atol=1e-6)
    assert torch.allclose(out[:, :, :3], color[:, :, :3])
    env.grid[0, 0, 0] = 0.5
    env.save(tmp_path / "environment.json")
    back = Environment.load(tmp_path / "environment.json")
    assert torch.allclose(back.grid, env.grid, atol=1e-5)
    (tmp_path / "bad.json").write_text('{"format": "other"}')
    with pytest.raises(InputError, match="not an environment"):
        Environment.load(tmp_path / "bad.json")


def test_sky_auto_follows_the_camera_layout():
    from types import SimpleNamespace

    from ssgwarp.procedural import rig_cameras, ring_cameras
    from ssgwarp.reconstruction import sky

    out = SimpleNamespace(cameras=rig_cameras(12, 8, 6), train_ids=list(range(12)))
    inward = SimpleNamespace(cameras=ring_cameras(12, 8, 6), train_ids=list(range(12)))
    assert sky.decide(out, "auto")["use"] and sky.decide(out, "auto")["layout"] == "inside-out"
    assert not sky.decide(inward, "auto")["use"]
    assert not sky.decide(out, "auto", backdrop=True)["use"]   # the backdrop's far shell stands for the sky
    assert sky.decide(inward, "on")["use"] and not sky.decide(out, "off")["use"]
    with pytest.raises(InputError, match="--sky"):
        sky.check_mode("maybe")
