"""Render a run or a splat file: ``ssgwarp render RUN_DIR|FILE --out DIR [--path N] [--split train|test|all]
[--video [FILE]]``.

``RUN_DIR`` is a reconstruction or a stylize output (:class:`~ssgwarp.services.runs.Run`; a
stylized run renders along its source reconstruction's cameras, on its recorded background).
Renders the run's scene along its own cameras (one PNG per camera, named after
the image) or along a smooth camera path through them (``frame_0000.png`` ...,
plus ``path_cameras.json``). :func:`smooth_path` is the path other stages reuse. A splat file without its
capture (any format :func:`ssgwarp.formats.registry.read_splat_file` reads) renders along an orbit made around its splats
(:mod:`ssgwarp.capture.orbit`; ``--views`` cameras, or ``--path N`` frames on the same loop), the choices in
``orbit.json``. ``--video`` also writes the frames as a GIF (or MP4) with
:func:`ssgwarp.core.imaging.write_video`, as ``stylize`` writes ``path.gif``.
"""
from __future__ import annotations

import logging

import numpy as np
import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.geometry import quat_to_rotmat, rotmat_to_quat
from ..raster.rendering import render_to_files

log = logging.getLogger("ssgwarp.evaluation.render")


def _tour(points: torch.Tensor) -> list[int]:
    """A short closed tour through ``points [C, 3]``: nearest-neighbour from point 0, then 2-opt."""
    c = points.shape[0]
    if c <= 3:
        return list(range(c))
    d = torch.cdist(points, points).numpy()
    order = [0]
    left = set(range(1, c))
    while left:
        last = order[-1]
        nxt = min(left, key=lambda j: (d[last, j], j))
        order.append(nxt)
        left.remove(nxt)
    improved, rounds = True, 0
    while improved and rounds < 50:  # 2-opt on the closed tour
        improved, rounds = False, rounds + 1
        for i in range(1, c - 1):
            for j in range(i + 1, c):
                a, b = order[i - 1], order[i]
                e, f = order[j], order[(j + 1) % c]
                if d[a, e] + d[b, f] < d[a, b] + d[e, f] - 1e-12:
                    order[i:j + 1] = order[i:j + 1][::-1]
                    improved = True
    return order


def _catmull_rom(p: torch.Tensor, t: torch.Tensor, closed: bool = True) -> torch.Tensor:
    """Uniform Catmull-Rom spline through the rows of ``p [K, D]`` at parameters ``t``.

    Closed: ``t`` in [0, K), the spline wraps around. Open: ``t`` in [0, K-1], the end
    points are repeated so the curve starts at ``p[0]`` and ends at ``p[-1]``.
    """
    k = p.shape[0]
    if closed:
        i = torch.floor(t).long() % k
        p0, p1, p2, p3 = p[(i - 1) % k], p[i], p[(i + 1) % k], p[(i + 2) % k]
    else:
        ext = torch.cat([p[:1], p, p[-1:]])
        i = torch.floor(t).long().clamp(0, k - 2)
        p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
    u = (t - i.to(t.dtype))[:, None] if not closed else (t - torch.floor(t))[:, None]
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


def smooth_path(cameras: Cameras, n_frames: int, *, max_keys: int = 16, closed: bool = True) -> Cameras:
    """``n_frames`` cameras on a smooth path through ``cameras``' centres and orientations.

    The cameras are ordered along a short closed tour (nearest neighbour + 2-opt); at
    most ``max_keys`` of them, evenly spaced along the tour, become key frames; centres
    and orientations (quaternions, sign-aligned, renormalised) follow a uniform
    Catmull-Rom spline through the key frames (a loop, or with ``closed=False`` an open
    path from the first key frame to the last), resampled at equal arc length. The
    intrinsics are the cameras' mean; names are ``frame_0000``... A single camera gives
    ``n_frames`` copies of it.
    """
    if n_frames < 1:
        raise InputError(f"smooth_path: n_frames must be >= 1, got {n_frames}")
    if len(cameras) == 0:
        raise InputError("smooth_path: no cameras")
    c2w = cameras.camtoworlds.double().cpu()
    centers = c2w[:, :3, 3]
    K = cameras.Ks.double().cpu().mean(dim=0)
    names = [f"frame_{i:04d}" for i in range(n_frames)]
    dev, dt = cameras.viewmats.device, cameras.viewmats.dtype
    if len(cameras) == 1:
        return Cameras(cameras.viewmats[:1].repeat(n_frames, 1, 1), cameras.Ks[:1].repeat(n_frames, 1, 1),
                       cameras.width, cameras.height, names)
    order = _tour(centers)
    if len(order) > max_keys:
        pick = np.linspace(0, len(order), max_keys, endpoint=False).round().astype(int)
        order = [order[i] for i in pick]
    P = centers[order]
    Q = rotmat_to_quat(c2w[order, :3, :3])
    for i in range(1, len(Q)):  # same hemisphere as the previous key: no flips
        if float(Q[i] @ Q[i - 1]) < 0:
            Q[i] = -Q[i]
    k = len(order)
    span = float(k) if closed else float(k - 1)
    dense_t = torch.linspace(0, span, 64 * k + 1, dtype=torch.float64)
    dense = _catmull_rom(P, dense_t, closed)
    s = torch.cat([torch.zeros(1, dtype=torch.float64), (dense[1:] - dense[:-1]).norm(dim=1).cumsum(0)])
    m = n_frames + 1 if closed else n_frames  # a loop does not repeat its first frame
    if float(s[-1]) <= 1e-12:
        t = torch.linspace(0, span, m, dtype=torch.float64)[:n_frames]
    else:
        target = torch.linspace(0, float(s[-1]), m, dtype=torch.float64)[:n_frames]
        j = torch.searchsorted(s, target).clamp(1, len(s) - 1)
        w = ((target - s[j - 1]) / (s[j] - s[j - 1]).clamp_min(1e-300)).clamp(0, 1)
        t = dense_t[j - 1] * (1 - w) + dense_t[j] * w
    pos = _catmull_rom(P, t, closed)
    # quaternions: the four keys of each segment sign-aligned to its start (no flips, also at the wrap)
    q = _catmull_rom_quats(Q, t, closed)
    quat = torch.nn.functional.normalize(q, dim=1)
    R = quat_to_rotmat(quat)
    c2w_new = torch.eye(4, dtype=torch.float64).repeat(n_frames, 1, 1)
    c2w_new[:, :3, :3] = R
    c2w_new[:, :3, 3] = pos
    viewmats = torch.linalg.inv(c2w_new)
    return Cameras(viewmats.to(device=dev, dtype=dt), K.to(device=dev, dtype=dt)[None].repeat(n_frames, 1, 1),
                   cameras.width, cameras.height, names)


def _catmull_rom_quats(Q: torch.Tensor, t: torch.Tensor, closed: bool) -> torch.Tensor:
    """Catmull-Rom on quaternions with the four keys of each segment sign-aligned to the segment's start."""
    k = Q.shape[0]
    if closed:
        i = torch.floor(t).long() % k
        keys = [Q[(i + o) % k] for o in (-1, 0, 1, 2)]
        u = (t - torch.floor(t))[:, None]
    else:
        ext = torch.cat([Q[:1], Q, Q[-1:]])
        i = torch.floor(t).long().clamp(0, k - 2)
        keys = [ext[i + o] for o in (0, 1, 2, 3)]
        u = (t - i.to(t.dtype))[:, None]
    ref = keys[1]
    p0, p1, p2, p3 = [torch.where((q * ref).sum(-1, keepdim=True) < 0, -q, q) for q in keys]
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


# the renders themselves: ssgwarp.raster.rendering (render_cameras: the old name, kept importable)
render_cameras = render_to_files
