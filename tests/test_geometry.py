"""ssgwarp.core.geometry: rotations, reprojection, nearest neighbours, against independent constructions."""
import math

import numpy as np
import pytest
import torch

from ssgwarp.core.geometry import (knn, knn_indices, knn_mean_distance, pixel_centers, project, quat_to_rotmat,
                              rotmat_to_quat, unproject)


def rodrigues(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation by ``angle`` about unit ``axis``: I + sin K + (1 - cos) K^2."""
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*axis.shape[:-1], 3, 3)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=axis.dtype) + s * K + (1 - c) * (K @ K)


def test_quaternions_match_axis_angle_and_round_trip():
    g = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(torch.randn(500, 3, generator=g, dtype=torch.float64), dim=-1)
    angle = torch.rand(500, generator=g, dtype=torch.float64) * 2 * math.pi
    q = torch.cat([torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * axis], -1)
    R = rodrigues(axis, angle)
    torch.testing.assert_close(quat_to_rotmat(q * 3.7), R, atol=1e-13, rtol=0)   # any norm
    back = rotmat_to_quat(R)
    assert bool((back[:, 0] >= 0).all())
    torch.testing.assert_close(back, q * torch.sign(q[:, :1]), atol=1e-12, rtol=0)  # q and -q: one rotation


@pytest.mark.parametrize("diag", [(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)])
def test_rotmat_to_quat_half_turns_and_identity(diag):
    """The trace is -1 for the half turns (the w formula breaks down there): the x, y, z branches."""
    R = torch.diag(torch.tensor(diag, dtype=torch.float64))
    q = rotmat_to_quat(R)
    assert torch.isfinite(q).all()
    torch.testing.assert_close(quat_to_rotmat(q), R, atol=1e-15, rtol=0)


def test_colmap_and_viewer_rotations_are_the_shared_ones():
    from ssgwarp.formats.colmap import qvec_to_rotmat, rotmat_to_qvec
    from ssgwarp.viewer import geometry as viewer_geometry

    q = np.array([0.3, -0.5, 0.2, 0.7])
    R = qvec_to_rotmat(q)
    assert np.allclose(R, quat_to_rotmat(torch.from_numpy(q)).numpy(), atol=1e-15)
    assert np.allclose(rotmat_to_qvec(R), q / np.linalg.norm(q), atol=1e-15)
    both = viewer_geometry.quat_to_rotmat(np.stack([q, np.zeros(4)]))
    assert np.allclose(both[0], R, atol=1e-15) and np.array_equal(both[1], np.eye(3))


def test_unproject_then_project_returns_the_pixel_centres():
    g = torch.Generator().manual_seed(1)
    H, W = 6, 9
    K = torch.tensor([[20.0, 0, 4.1], [0, 18.0, 3.2], [0, 0, 1]], dtype=torch.float64)
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
    view = torch.eye(4, dtype=torch.float64)
    view[:3, :3] = rodrigues(axis, torch.tensor(0.7, dtype=torch.float64))
    view[:3, 3] = torch.tensor([0.2, -0.1, 1.5], dtype=torch.float64)
    depth = 1.0 + torch.rand(H, W, generator=g, dtype=torch.float64)
    pts = unproject(depth, K, view)
    uv, z = project(pts, view, K)
    torch.testing.assert_close(uv, pixel_centers(H, W, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(z, depth, atol=1e-12, rtol=0)
    assert pixel_centers(2, 3)[1, 2].tolist() == [2.5, 1.5]


@pytest.mark.parametrize("block", [7, 64, 1 << 25])
def test_knn_is_exact_in_any_block_size(block):
    """Blocks smaller than a row of queries, a few points per block, or the whole matrix at once:
    the same neighbours as a full distance matrix; the excluded index never comes back."""
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(150, 3, generator=g, dtype=torch.float64)
    q = torch.arange(0, 150, 4)
    d, i = knn(pts[q], pts, 6, exclude=q, block=block)
    full = torch.cdist(pts[q], pts)
    full[torch.arange(len(q)), q] = float("inf")
    top = full.topk(6, largest=False)
    assert torch.equal(i, top.indices)
    torch.testing.assert_close(d, top.values, atol=1e-12, rtol=0)
    assert not bool((i == q[:, None]).any())
    assert torch.equal(knn_indices(pts[q], pts, 6, exclude=q, block=block), i)
    # k beyond the points available is capped; no queries, no rows
    assert knn(pts[:3], pts[:3], 10, exclude=torch.arange(3))[1].shape == (3, 2)
    assert knn(pts[:0], pts, 4)[0].shape == (0, 4)


def test_direct_distances_equal_cdist_and_knn_on_them(monkeypatch):
    """The distances CUDA uses (coordinate differences formed as one tensor: torch's exact cdist kernel is
    slow there) equal cdist's exact ones, keep a repeated point at 0 in float32 far from the origin, and
    give knn the same neighbours (the direct form forced here on the CPU)."""
    from ssgwarp.core import geometry
    g = torch.Generator().manual_seed(5)
    pts = torch.rand(300, 3, generator=g, dtype=torch.float64)
    ref = torch.cdist(pts[:40], pts, compute_mode="donot_use_mm_for_euclid_dist")
    torch.testing.assert_close(geometry.pairwise_distances(pts[:40], pts, direct=True), ref, atol=1e-14, rtol=0)
    far = torch.rand(50, 3, generator=g) + 50.0
    d = geometry.pairwise_distances(far, torch.cat([far, far + 1e-4]), direct=True)
    assert torch.equal(torch.diagonal(d[:, :50]), torch.zeros(50))
    assert bool((torch.diagonal(d[:, 50:]) > 0).all())
    q = torch.arange(0, 300, 7)
    want = knn(pts[q], pts, 5, exclude=q, block=64)
    original = geometry.pairwise_distances
    monkeypatch.setattr(geometry, "pairwise_distances", lambda a, b: original(a, b, direct=True))
    got = knn(pts[q], pts, 5, exclude=q, block=64)
    assert torch.equal(got[1], want[1])
    torch.testing.assert_close(got[0], want[0], atol=1e-14, rtol=0)


def test_knn_in_float32_finds_repeated_points_at_distance_zero():
    """Far from the origin, ``|a|^2 + |b|^2 - 2ab`` loses the small distances in float32 (cdist's default
    for large inputs); knn takes coordinate differences, so a repeated point is found at exactly 0."""
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(400, 3, generator=g) + 50.0
    pts = torch.cat([pts, pts[:100] + torch.tensor([0.0, 0.0, 1e-4])])
    d, i = knn(pts[:100], pts, 1, exclude=torch.arange(100))
    assert torch.equal(i[:, 0], torch.arange(400, 500))
    torch.testing.assert_close(d[:, 0], (pts[400:] - pts[:100]).norm(dim=1), atol=1e-6, rtol=0)


def test_knn_mean_distance():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [7, 0, 0]])
    torch.testing.assert_close(knn_mean_distance(pts, k=2), torch.tensor([2.0, 1.5, 2.5, 5.0]))
    assert knn_mean_distance(pts[:1]).tolist() == [1.0]


@pytest.mark.parametrize("spread", ["clusters", "line", "crowded"])
def test_knn_table_gives_the_brute_force_neighbours(spread, monkeypatch):
    """Every point's k nearest others through the grid equal the full distance matrix's (by distance:
    the same distances, nearest first), itself never among them, on points the grid suits badly:
    dense clusters with far outliers (cubes with hundreds of points, lone points the grid cannot
    answer for), points on a line (a flat bounding box), and with cubes holding more candidates than
    the grid takes (those points searched by brute force); small query chunks and candidate batches
    change nothing."""
    import ssgwarp.core.geometry as geometry
    from ssgwarp.core.geometry import knn_table

    if spread == "crowded":
        monkeypatch.setattr(geometry, "GRID_MAX_CANDIDATES", 40)
        monkeypatch.setattr(geometry, "GRID_BATCH", 500)

    g = torch.Generator().manual_seed(4)
    if spread in ("clusters", "crowded"):
        centres = torch.rand(5, 3, generator=g, dtype=torch.float64) * 10
        pts = torch.cat([centres[torch.randint(0, 5, (900,), generator=g)]
                         + 0.05 * torch.randn(900, 3, generator=g, dtype=torch.float64),
                         torch.rand(12, 3, generator=g, dtype=torch.float64) * 40 - 15])
    else:
        t = torch.rand(600, 1, generator=g, dtype=torch.float64)
        pts = t * torch.tensor([[1.0, 2.0, -0.5]], dtype=torch.float64)
    n = len(pts)
    full = torch.cdist(pts, pts)
    full.fill_diagonal_(float("inf"))
    want = full.topk(6, largest=False).values
    for chunk in (1 << 15, 97):
        tab = knn_table(pts, 6, chunk=chunk)
        assert tab.shape == (n, 6)
        assert not bool((tab == torch.arange(n)[:, None]).any())
        assert bool((tab[:, 1:] != tab[:, :-1]).all())
        got = full.gather(1, tab)
        torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    # float32 points: the same neighbours (distances taken in float64)
    tab32 = knn_table(pts.float(), 6)
    torch.testing.assert_close(full.gather(1, tab32), want, atol=1e-6, rtol=0)
    assert knn_table(pts[:3], 10).shape == (3, 2) and knn_table(pts[:1], 4).shape == (1, 0)


def test_knn_mean_distance_of_a_large_cloud_goes_through_the_grid(monkeypatch):
    """Above KNN_TABLE_MIN points (3-D), the mean neighbour distance comes from knn_table's grid and
    equals the blocks' answer."""
    from ssgwarp.core import geometry as G

    g = torch.Generator().manual_seed(7)
    centres = torch.randn(8, 3, generator=g) * 3
    pts = centres[torch.randint(0, 8, (3000,), generator=g)] + torch.randn(3000, 3, generator=g) * 0.2
    want = G.knn(pts, pts, 3, exclude=torch.arange(3000))[0].mean(1)
    calls = []
    table = G.knn_table
    monkeypatch.setattr(G, "knn_table", lambda *a, **kw: calls.append(1) or table(*a, **kw))
    monkeypatch.setattr(G, "KNN_TABLE_MIN", 1000)
    got = G.knn_mean_distance(pts, k=3)
    assert calls and got.dtype == pts.dtype
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    monkeypatch.setattr(G, "KNN_TABLE_MIN", 5000)
    calls.clear()
    torch.testing.assert_close(G.knn_mean_distance(pts, k=3), want, atol=0, rtol=0)
    assert not calls

