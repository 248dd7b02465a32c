"""Geometry shared by the stages: rotations, pixel reprojection, nearest neighbours (torch only).

- Rotations: :func:`quat_to_rotmat` (wxyz quaternions of any norm, the convention of the
  rasterizer, gsplat and COLMAP) and its inverse :func:`rotmat_to_quat` (``w >= 0``).
- Reprojection with pinhole intrinsics ``K [3, 3]`` and world-to-camera ``viewmat [4, 4]``, pixel
  centres at integer + 0.5 (the rasterizer's): :func:`pixel_centers`, :func:`unproject` (z-depth
  image to world points), :func:`project` (world points to pixels and camera z).
- Exact k-nearest neighbours in bounded memory: :func:`knn` (distances and indices, chunked over
  queries and points), :func:`knn_indices`, :func:`knn_mean_distance`; :func:`knn_table`, every
  3D point's neighbours among the others through a uniform grid (brute force where the grid cannot
  prove the answer).
"""
from __future__ import annotations

from typing import Optional

import torch

Tensor = torch.Tensor
# entries of one block of the distance matrix in knn (2^27: 512 MiB in float32; 60k points, k=3, one
# thread: 13.7 s against 12.4 s for one 4096-row block per query chunk over all points, which grows
# without bound; 14.5 s with 2^25)
KNN_BLOCK = 1 << 27
KNN_BLOCK_CUDA = 1 << 25  # on CUDA (differences of 3-D points: 400 MB at a time)
# points above which knn_mean_distance (3-D) goes through knn_table's grid instead of knn's blocks
KNN_TABLE_MIN = 20_000


# -- rotations ----------------------------------------------------------------------------------

def quat_to_rotmat(quats: Tensor, normalize: bool = True) -> Tensor:
    """``[..., 3, 3]`` rotations of wxyz quaternions ``[..., 4]`` (normalised here unless
    ``normalize=False``: the caller's are unit already). A zero quaternion gives NaN."""
    q = quats / torch.linalg.vector_norm(quats, dim=-1, keepdim=True) if normalize else quats
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit wxyz quaternions ``[..., 4]`` (``w >= 0``) of rotation matrices ``[..., 3, 3]``.

    Per matrix the formula of its largest term among the trace and the diagonal (w, x, y or z
    largest), so the division is by the largest candidate denominator (no cancellation)."""
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    tr = r00 + r11 + r22

    def four(t: Tensor) -> Tensor:  # 4 times the largest component, from 1 + 4 c^2 - 1 = t
        return 2.0 * torch.sqrt(t.clamp_min(1e-30))

    sw, sx = four(tr + 1.0), four(1.0 + r00 - r11 - r22)
    sy, sz = four(1.0 + r11 - r00 - r22), four(1.0 + r22 - r00 - r11)
    qw = torch.stack([0.25 * sw, (r21 - r12) / sw, (r02 - r20) / sw, (r10 - r01) / sw], -1)
    qx = torch.stack([(r21 - r12) / sx, 0.25 * sx, (r01 + r10) / sx, (r02 + r20) / sx], -1)
    qy = torch.stack([(r02 - r20) / sy, (r01 + r10) / sy, 0.25 * sy, (r12 + r21) / sy], -1)
    qz = torch.stack([(r10 - r01) / sz, (r02 + r20) / sz, (r12 + r21) / sz, 0.25 * sz], -1)
    use_w = tr > 0
    use_x = ~use_w & (r00 > r11) & (r00 > r22)
    use_y = ~use_w & ~use_x & (r11 > r22)
    q = torch.where(use_w[..., None], qw, torch.where(use_x[..., None], qx, torch.where(use_y[..., None], qy, qz)))
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


# -- reprojection -------------------------------------------------------------------------------

def pixel_centers(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """``[H, W, 2]`` (x, y) pixel-centre coordinates ``(j + 0.5, i + 0.5)``."""
    ys = torch.arange(height, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], dim=-1)


def unproject(depth: Tensor, K: Tensor, viewmat: Tensor) -> Tensor:
    """World points ``[H, W, 3]`` of the pixel centres at z-depth ``depth [H, W]`` (camera
    ``K [3, 3]``, world-to-camera ``viewmat [4, 4]``)."""
    H, W = depth.shape
    uv = pixel_centers(H, W, depth.device, depth.dtype)
    K = K.to(depth)
    x = (uv[..., 0] - K[0, 2]) / K[0, 0] * depth
    y = (uv[..., 1] - K[1, 2]) / K[1, 1] * depth
    pc = torch.stack([x, y, depth], dim=-1)
    c2w = torch.linalg.inv(viewmat.to(depth))
    return pc @ c2w[:3, :3].T + c2w[:3, 3]


def project(points: Tensor, viewmat: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates ``[..., 2]`` and camera z ``[...]`` of world ``points [..., 3]`` (points
    at z = 0 are divided by 1e-12: test ``z > 0`` before using their pixels)."""
    viewmat, K = viewmat.to(points), K.to(points)
    pc = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = pc[..., 2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    u = K[0, 0] * pc[..., 0] / zs + K[0, 2]
    v = K[1, 1] * pc[..., 1] / zs + K[1, 2]
    return torch.stack([u, v], dim=-1), z


# -- nearest neighbours ---------------------------------------------------------------------------

def pairwise_distances(q: Tensor, p: Tensor, direct: Optional[bool] = None) -> Tensor:
    """``[M, P]`` Euclidean distances of ``q [M, D]`` to ``p [P, D]`` from the coordinate differences (exact
    near 0, where the matrix-product form loses the small distances to cancellation). ``direct`` (default:
    on CUDA) forms the differences as one tensor; otherwise torch's ``cdist`` without the matrix product,
    whose CUDA kernel is slow (an H200, 2026-11-28: 135 ms for 1,000 x 134k points, against a few ms)."""
    if direct if direct is not None else q.is_cuda:
        return (q[:, None, :] - p[None, :, :]).square_().sum(-1).sqrt_()
    return torch.cdist(q, p, compute_mode="donot_use_mm_for_euclid_dist")


def knn(queries: Tensor, points: Tensor, k: int, *, exclude: Optional[Tensor] = None,
        block: int = KNN_BLOCK) -> tuple[Tensor, Tensor]:
    """Exact ``k`` nearest ``points [P, D]`` of each of ``queries [M, D]`` (Euclidean):
    ``(distances [M, k], indices [M, k])``, nearest first.

    ``exclude [M]``: an index into ``points`` per query never returned (e.g. the query itself).
    ``k`` is capped at the points available. The distance matrix is formed in blocks of at most
    ``block`` entries (queries by points), keeping a running best ``k`` per query."""
    M, P = queries.shape[0], points.shape[0]
    if queries.is_cuda:  # (the blocks' differences are made whole on CUDA: bytes = 4 x D x block)
        block = min(block, KNN_BLOCK_CUDA)
    k = max(0, min(int(k), P - (1 if exclude is not None else 0)))
    dev = queries.device
    out_d = torch.empty(M, k, dtype=queries.dtype, device=dev)
    out_i = torch.empty(M, k, dtype=torch.long, device=dev)
    if M == 0 or k == 0:
        return out_d, out_i
    pc = max(1, min(P, block // min(M, 4096)))
    qc = max(1, min(M, block // pc))
    for q0 in range(0, M, qc):
        q = queries[q0:q0 + qc]
        m = q.shape[0]
        best_d = torch.empty(m, 0, dtype=queries.dtype, device=dev)
        best_i = torch.empty(m, 0, dtype=torch.long, device=dev)
        for p0 in range(0, P, pc):
            d = pairwise_distances(q, points[p0:p0 + pc])
            n = d.shape[1]
            if exclude is not None:  # the excluded point, where it falls in this block, at infinity
                e = exclude[q0:q0 + m, None] - p0
                inside = (e >= 0) & (e < n)
                e = e.clamp(0, n - 1)
                d.scatter_(1, e, torch.where(inside, float("inf"), d.gather(1, e)))
            top = d.topk(min(k, n), dim=1, largest=False)    # this block's best, then merged
            if best_d.shape[1]:
                vals = torch.cat([best_d, top.values], dim=1)
                idx = torch.cat([best_i, top.indices + p0], dim=1)
                merged = vals.topk(min(k, vals.shape[1]), dim=1, largest=False)
                best_d, best_i = merged.values, idx.gather(1, merged.indices)
            else:
                best_d, best_i = top.values, top.indices + p0
        out_d[q0:q0 + m], out_i[q0:q0 + m] = best_d, best_i
    return out_d, out_i


def knn_indices(queries: Tensor, points: Tensor, k: int, *, exclude: Optional[Tensor] = None,
                block: int = KNN_BLOCK) -> Tensor:
    """``[M, k]`` indices of each query's ``k`` nearest points (:func:`knn`)."""
    return knn(queries, points, k, exclude=exclude, block=block)[1]


def knn_mean_distance(xyz: Tensor, k: int = 3) -> Tensor:
    """``[N]`` mean distance of each point to its ``k`` nearest other points (1 for a lone point)."""
    n = xyz.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=xyz.dtype, device=xyz.device)
    if xyz.shape[1] == 3 and n > KNN_TABLE_MIN:  # (a grid: linear time; 100k points 2-3 s against ~30 s)
        idx = knn_table(xyz, k)
        x = xyz.detach().double()
        return torch.linalg.vector_norm(x[idx] - x[:, None], dim=-1).mean(dim=1).to(xyz.dtype)
    d, _ = knn(xyz, xyz, k, exclude=torch.arange(n, device=xyz.device))
    return d.mean(dim=1)


# points per grid cell that knn_table aims for (on points spread evenly: 27 cells, about 54 candidates)
GRID_OCCUPANCY = 2.0
# a point with more grid candidates than this goes to the brute-force search; candidates per batch
GRID_MAX_CANDIDATES = 4096
GRID_BATCH = 1 << 21


def knn_table(points: Tensor, k: int, *, chunk: int = 1 << 15) -> Tensor:
    """``[P, k]`` indices of each of ``points [P, 3]``'s ``k`` nearest other points, nearest first
    (the same neighbours as :func:`knn_indices` with each point excluded, up to ties of distance).

    The points are binned into a uniform grid of cubes of side ``h`` (about
    :data:`GRID_OCCUPANCY` points per cube of the box holding the middle 90 % of the points along
    each axis, so that a few far points do not coarsen it); a point's candidates are the points of
    its own and the 26 surrounding cubes, whose distances are computed directly in float64. The
    answer is exact when the k-th candidate is nearer than every point outside those cubes (closer
    than ``h`` plus the point's distance to its own cube's nearest face); the other points (sparse
    regions, fewer than k candidates, or more than :data:`GRID_MAX_CANDIDATES` in dense ones) go
    through :func:`knn` over all points. Memory is bounded: ``chunk`` queries' cube ranges and at
    most :data:`GRID_BATCH` candidates at a time.
    """
    P = points.shape[0]
    k = max(0, min(int(k), P - 1))
    dev = points.device
    out = torch.empty(P, k, dtype=torch.long, device=dev)
    if P == 0 or k == 0:
        return out
    x = points.detach().double()
    lo = x.min(0).values
    extent = (x.max(0).values - lo).clamp_min(1e-12)
    q = torch.quantile(x[:: max(1, P // 100_000)], torch.tensor([0.05, 0.95], dtype=x.dtype, device=dev), dim=0)
    core = (q[1] - q[0]).clamp_min(1e-12)
    h = float((core.prod() * GRID_OCCUPANCY / (0.9 ** 3 * P)) ** (1.0 / 3.0))
    h = max(h, float(extent.max()) / 1024.0)    # at most 1024 cubes along an axis (keys fit easily)
    cell = ((x - lo) / h).floor().long()
    dims = cell.max(0).values + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = torch.argsort(key, stable=True)
    skey = key[order]
    offs = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=dev)] * 3, indexing="ij"), -1).reshape(27, 3)
    # distance from each point to the nearest face of its cube: what the 27 cubes are sure to cover
    inside = x - lo - cell.double() * h
    reach = h + torch.minimum(inside, h - inside).min(1).values
    brute = []
    for q0 in range(0, P, chunk):
        qs = torch.arange(q0, min(P, q0 + chunk), device=dev)
        nb = cell[qs, None, :] + offs[None]                                   # [Q, 27, 3]
        ok = ((nb >= 0) & (nb < dims)).all(-1)
        nkey = (nb[..., 0] * dims[1] + nb[..., 1]) * dims[2] + nb[..., 2]
        start = torch.searchsorted(skey, nkey)
        cnt = torch.where(ok, torch.searchsorted(skey, nkey, right=True) - start, 0)
        per_q = cnt.sum(1)
        light = (per_q > k) & (per_q <= GRID_MAX_CANDIDATES)                  # k others besides itself
        brute.append(qs[~light])
        sub = torch.nonzero(light).flatten()
        ends = torch.cumsum(per_q[sub], 0)
        b0 = 0
        while b0 < len(sub):
            b1 = int(torch.searchsorted(ends, int(ends[b0 - 1] if b0 else 0) + GRID_BATCH, right=True))
            b1 = max(b1, b0 + 1)
            rows = sub[b0:b1]
            good, nbrs = _grid_neighbours(x, qs[rows], start[rows], cnt[rows], order, k, reach)
            out[qs[rows][good]] = nbrs[good]
            brute.append(qs[rows][~good])
            b0 = b1
    rest = torch.cat(brute)
    if rest.numel():
        out[rest] = knn_indices(x[rest], x, k, exclude=rest)   # (float64: float32 distance sums cancel)
    return out


def _grid_neighbours(x: Tensor, q: Tensor, start: Tensor, cnt: Tensor, order: Tensor, k: int, reach: Tensor):
    """For queries ``q`` (each with at least k + 1 candidates) whose 27 cubes hold the sorted-point
    ranges ``start, cnt [Q, 27]``: ``(good [Q] bool, neighbours [Q, k])``, good where the k nearest
    candidates are provably the k nearest points (the k-th nearer than ``reach``)."""
    dev = x.device
    per_q = cnt.sum(1)
    flat_cnt = cnt.reshape(-1)
    first = torch.cumsum(flat_cnt, 0) - flat_cnt
    pos = torch.arange(int(flat_cnt.sum()), device=dev) - torch.repeat_interleave(first, flat_cnt)
    cand = order[torch.repeat_interleave(start.reshape(-1), flat_cnt) + pos]
    qi = torch.repeat_interleave(q, per_q)
    d = (x[cand] - x[qi]).square().sum(1)
    d = torch.where(cand == qi, float("inf"), d)
    # grouped by query, nearest first: sort by distance, then (stably) by query
    o = torch.argsort(d, stable=True)
    o = o[torch.argsort(qi[o], stable=True)]
    sel = o[(torch.cumsum(per_q, 0) - per_q)[:, None] + torch.arange(k, device=dev)]
    good = d[sel[:, -1]].sqrt() < reach[q]
    return good, cand[sel]
