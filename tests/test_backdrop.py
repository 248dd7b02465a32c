"""The backdrop decision rests on evidence that the photos see far content (ssgwarp.reconstruction.backdrop):
synthetic orbit captures with known geometry, rendered by ray casting."""
import math

import torch

from ssgwarp.capture.datasets import SceneData
from ssgwarp.procedural import ring_cameras
from ssgwarp.reconstruction.backdrop import MIN_FAR, far_evidence, plan_backdrop


def _noise(u, v, res, seed):
    """A random texture (values 0.2-0.8 on a res[0] x res[1] grid, bilinear) at coordinates u, v in [0, 1]
    (u wraps around)."""
    tex = 0.2 + 0.6 * torch.rand(1, 1, res[1], res[0], generator=torch.Generator().manual_seed(seed))
    tex = torch.cat([tex, tex[..., :1]], -1)
    g = torch.stack([u.remainder(1.0) * 2 - 1, v.clamp(0, 1) * 2 - 1], -1)[None].float()
    return torch.nn.functional.grid_sample(tex, g, align_corners=True)[0, 0].double()


def synthetic_capture(far: str, views: int = 16, width: int = 64, height: int = 48, seed: int = 0):
    """An orbit around a textured ball on a textured round table; beyond the table ``far`` = "textured"
    (a patterned sphere of radius 40), "plain" (a flat grey one), or "wall" (a patterned cylinder of radius 6
    whose surface also gets points). Points: sparse samples of the ball, the table (and the wall)."""
    cams = ring_cameras(views, width, height, radius=4.0, elevation_deg=18.0, target=(0.0, 0.0, 0.0))
    c2w = cams.camtoworlds.double()
    K = cams.Ks.double()
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64) + 0.5,
                            torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    images = []
    for i in range(views):
        d = torch.stack([(xs - K[i, 0, 2]) / K[i, 0, 0], (ys - K[i, 1, 2]) / K[i, 1, 1], torch.ones_like(xs)], -1)
        d = torch.nn.functional.normalize(d @ c2w[i, :3, :3].T, dim=-1)
        o = c2w[i, :3, 3]
        inf = torch.full(d.shape[:2], float("inf"), dtype=torch.float64)
        # ball |x| = 1
        bq = (d * o).sum(-1)
        disc = bq ** 2 - (o @ o - 1)
        t_ball = torch.where(disc > 0, -bq - disc.clamp(min=0).sqrt(), inf)
        # table z = -1, radius 3
        t_tab = torch.where(d[..., 2] < 0, (-1 - o[2]) / d[..., 2], inf)
        hit = o + t_tab[..., None] * d
        t_tab = torch.where(hit[..., :2].norm(dim=-1) <= 3, t_tab, inf)
        if far == "wall":  # cylinder radius 6 about z
            a = (d[..., :2] ** 2).sum(-1)
            bb = (d[..., :2] * o[:2]).sum(-1)
            t_far = (-bb + (bb ** 2 - a * (o[:2] @ o[:2] - 36)).sqrt()) / a
        else:
            bq2 = (d * o).sum(-1)
            t_far = -bq2 + (bq2 ** 2 - (o @ o - 1600)).sqrt()
        t = torch.stack([t_ball, t_tab, t_far]).min(0)
        p = o + t.values[..., None] * d
        x, y, z = p.unbind(-1)
        ball = _noise(torch.atan2(y, x) / (2 * math.pi), (z + 1) / 2, (40, 20), 1)
        table = _noise((x + 3) / 6, (y + 3) / 6, (40, 40), 2)
        if far == "wall":
            ang = torch.atan2(y, x)
            back = _noise(ang / (2 * math.pi), (z + 1) / 6, (100, 20), 3)
        elif far == "textured":
            ang, el = torch.atan2(y, x), torch.asin((z / 40).clamp(-1, 1))
            back = _noise(ang / (2 * math.pi), el / math.pi + 0.5, (120, 60), 4)
        else:
            back = torch.full_like(x, 0.55)
        g = torch.stack([ball, table, back]).gather(0, t.indices[None])[0]
        images.append(torch.stack([g, 0.8 * g + 0.1, 0.6 * g + 0.2], -1))
    gen = torch.Generator().manual_seed(seed)
    n = 150
    u = torch.rand(n, 2, generator=gen, dtype=torch.float64)
    ball_pts = torch.stack([torch.sqrt(1 - (2 * u[:, 0] - 1) ** 2) * torch.cos(2 * math.pi * u[:, 1]),
                            torch.sqrt(1 - (2 * u[:, 0] - 1) ** 2) * torch.sin(2 * math.pi * u[:, 1]),
                            2 * u[:, 0] - 1], 1)
    r = 3 * torch.rand(n, generator=gen, dtype=torch.float64).sqrt()
    a = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
    tab_pts = torch.stack([r * torch.cos(a), r * torch.sin(a), torch.full_like(r, -1.0)], 1)
    pts = [ball_pts, tab_pts]
    if far == "wall":
        a = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
        pts.append(torch.stack([6 * torch.cos(a), 6 * torch.sin(a), -1 + 4 * torch.rand(n, generator=gen, dtype=torch.float64)], 1))
    xyz = torch.cat(pts).float()
    ids = list(range(views))
    return SceneData(cameras=cams, images=torch.stack(images).float(), names=list(cams.names), train_ids=ids[1::1],
                     test_ids=[], points=(xyz, torch.full_like(xyz, 0.5)), points_source="colmap")


def test_far_background_seen_beyond_the_points_earns_a_backdrop():
    data = synthetic_capture("textured")
    plan = plan_backdrop(data, data.points[0])
    assert plan.coverage < 0.9 and plan.layout == "object-centred"
    assert plan.use and plan.evidence["far"] >= 2 * MIN_FAR and "beyond twice their depth" in plan.why
    assert plan.record()["far_cells"] == round(plan.evidence["far"], 4)


def test_uncovered_cells_without_far_content_earn_none():
    # an object on a plain (textureless) ground: the uncovered cells carry no evidence
    plain = synthetic_capture("plain")
    p = plan_backdrop(plain, plain.points[0])
    assert p.coverage < 0.9 and not p.use and p.evidence["far"] == 0.0
    # a textured wall close behind the object, with a few points on it (sparse COLMAP points): the uncovered
    # cells are textured, but the sweep finds them at the points' depth
    wall = synthetic_capture("wall")
    p = plan_backdrop(wall, wall.points[0])
    assert p.coverage < 0.9 and not p.use and p.evidence["textured"] > 0.5 and p.evidence["far"] < MIN_FAR
    # the same wall without its points: it lies beyond the object's points but within twice their depth
    obj = wall.points[0][:300]
    e = far_evidence(wall.cameras, wall.images, obj, wall.train_ids)
    assert e["far"] < MIN_FAR


def test_rays_of_a_view_that_sees_no_point_are_uniform_in_log_depth_not_crowded_at_the_camera():
    """A view with no initial point in front of it starts its backdrop rays at the cameras' radius; uniform in
    inverse depth out to the far radius (50x) 83 % of them would lie within 5.5 radii of the camera (floaters on
    the procedural inside-out capture: 80 % of its held-out pixels); uniform in log depth, 44 %. Views that see
    points keep inverse depth from their points' median depth."""
    import numpy as np

    from ssgwarp.capture.loaders import random_points_in_frusta

    cams = ring_cameras(2, 32, 24)
    images = torch.rand(2, 24, 32, 3, generator=torch.Generator().manual_seed(0))
    near, far = np.array([0.3, 0.3]), np.array([15.0, 15.0])
    n = 20_000
    depth = {}
    for name, log in (("inverse", None), ("log", np.array([True, True])), ("mixed", np.array([True, False]))):
        xyz, rgb = random_points_in_frusta(cams, images, near, far, n, seed=1, log_depth=log)
        d = (xyz.double() - cams.camtoworlds[:, :3, 3].double()[:, None]).norm(dim=2).min(0).values   # (nearest)
        depth[name] = d
        assert xyz.shape == (n, 3) and rgb.shape == (n, 3) and bool(((d > 0.29) & (d < 15.01 * 1.5)).all())
    close = {k: float((v < 1.65).double().mean()) for k, v in depth.items()}
    assert abs(close["inverse"] - 0.83) < 0.03 and abs(close["log"] - 0.44) < 0.03, close
    assert close["log"] < close["mixed"] < close["inverse"]
