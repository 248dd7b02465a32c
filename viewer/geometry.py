"""Geometry the viewer draws, as plain numpy (no VTK here; rotations from :mod:`ssgwarp.core.geometry`).

Everything is float64 numpy; meshes come back as ``(points, cells)`` with
``cells`` in VTK's flat connectivity layout (``[n, i0, ..., i{n-1}, n, ...]``)
so that ``pyvista.PolyData(points, faces=cells)`` / ``lines=cells`` takes them
directly.
"""
from __future__ import annotations

import numpy as np
import torch

from ssgwarp.core import geometry


def quat_to_rotmat(quats: np.ndarray) -> np.ndarray:
    """``[N, 4]`` wxyz quaternions (any norm) → ``[N, 3, 3]`` rotation matrices
    (:func:`ssgwarp.core.geometry.quat_to_rotmat`). A zero quaternion gives the identity.
    """
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    return geometry.quat_to_rotmat(torch.from_numpy(q), normalize=False).numpy()


def unit_sphere(theta_res: int = 12, phi_res: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A latitude-longitude unit sphere: ``(vertices [V, 3], triangles [T, 3])``.

    ``V = 2 + (phi_res - 1) * theta_res``, ``T = 2 * theta_res * (phi_res - 1)``.
    """
    if theta_res < 3 or phi_res < 2:
        raise ValueError("unit_sphere: need theta_res >= 3 and phi_res >= 2")
    phi = np.linspace(0.0, np.pi, phi_res + 1)[1:-1]            # ring latitudes (no poles)
    theta = np.linspace(0.0, 2 * np.pi, theta_res, endpoint=False)
    ring = np.stack([np.sin(phi)[:, None] * np.cos(theta)[None], np.sin(phi)[:, None] * np.sin(theta)[None],
                     np.repeat(np.cos(phi)[:, None], theta_res, axis=1)], axis=-1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]], axis=0)
    top, bottom = 0, len(verts) - 1
    tris = []
    j = np.arange(theta_res)
    jn = (j + 1) % theta_res
    tris.append(np.stack([np.full(theta_res, top), 1 + j, 1 + jn], -1))
    for r in range(phi_res - 2):
        a, b = 1 + r * theta_res, 1 + (r + 1) * theta_res
        tris.append(np.stack([a + j, b + j, b + jn], -1))
        tris.append(np.stack([a + j, b + jn, a + jn], -1))
    last = 1 + (phi_res - 2) * theta_res
    tris.append(np.stack([last + j, np.full(theta_res, bottom), last + jn], -1))
    return verts, np.concatenate(tris, axis=0)


def ellipsoid_glyphs(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, sigma: float = 1.0,
                     theta_res: int = 12, phi_res: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One oriented ellipsoid per Gaussian, merged into a single triangle mesh.

    Args:
        means: ``[N, 3]`` centres. quats: ``[N, 4]`` wxyz. scales: ``[N, 3]`` per-axis standard deviations.
        sigma: the ellipsoid's semi-axes are ``sigma * scales`` (rotated by the quaternion).

    Returns:
        ``(points [N*V, 3], faces (VTK flat, 4 ints per triangle), owner [N*V])`` where
        ``owner`` is the Gaussian (row of ``means``) each vertex belongs to.
    """
    means = np.asarray(means, dtype=np.float64)
    n = len(means)
    verts, tris = unit_sphere(theta_res, phi_res)
    R = quat_to_rotmat(quats)                                        # [N,3,3]
    axes = R * (sigma * np.asarray(scales, dtype=np.float64))[:, None, :]  # columns scaled
    pts = np.einsum("nij,vj->nvi", axes, verts) + means[:, None, :]      # [N,V,3]
    offsets = (np.arange(n) * len(verts))[:, None, None]
    t = (tris[None] + offsets).reshape(-1, 3)
    faces = np.concatenate([np.full((len(t), 1), 3), t], axis=1).ravel().astype(np.int64)
    owner = np.repeat(np.arange(n), len(verts))
    return pts.reshape(-1, 3), faces, owner


# apex 0, corners 1..4 (top-left, top-right, bottom-right, bottom-left), up tip 5
_FRUSTUM_SEGMENTS = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 2), (2, 3), (3, 4), (4, 1), (1, 5), (5, 2)]
SEGMENTS_PER_FRUSTUM = len(_FRUSTUM_SEGMENTS)


def frustum_lines(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
                  depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Wire-frame frustums of C pinhole cameras (OpenCV convention, world-to-camera ``viewmats``).

    Each camera gives 6 points (apex, the 4 image corners at ``depth`` along
    the optical axis, and the tip of an "up" triangle above the image's top
    edge) and 10 segments (4 apex-corner edges, 4 rectangle edges, 2 for the
    up triangle).

    Returns:
        ``(points [C*6, 3], lines (VTK flat, 3 ints per segment))``.
    """
    viewmats = np.asarray(viewmats, dtype=np.float64)
    Ks = np.asarray(Ks, dtype=np.float64)
    c2w = np.linalg.inv(viewmats)
    pix = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height], [width / 2, -0.15 * height]])
    out, lines = [], []
    for i in range(len(viewmats)):
        Kinv = np.linalg.inv(Ks[i])
        rays = (Kinv @ np.concatenate([pix, np.ones((5, 1))], axis=1).T).T   # z = 1
        cam_pts = np.concatenate([np.zeros((1, 3)), rays * depth], axis=0)    # [6,3]
        world = cam_pts @ c2w[i, :3, :3].T + c2w[i, :3, 3]
        out.append(world)
        b = 6 * i
        lines += [[2, b + s, b + e] for s, e in _FRUSTUM_SEGMENTS]
    pts = np.concatenate(out, axis=0) if out else np.zeros((0, 3))
    return pts, np.asarray(lines, dtype=np.int64).ravel()


def subsample_indices(n: int, budget: int | None, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``budget`` of ``n`` items (all of them when ``budget`` is None or >= n).

    The choice is uniform at random and repeatable for a ``seed``.
    """
    if budget is None or budget >= n:
        return np.arange(n)
    if budget <= 0:
        raise ValueError(f"point budget must be positive, got {budget}")
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=budget, replace=False))


def point_radii(scales: np.ndarray, sigma: float = 1.0, cap: float | None = None) -> np.ndarray:
    """``[N]`` disc radius per Gaussian: ``sigma`` times the geometric mean of its 3 scales, at most ``cap``."""
    s = np.asarray(scales, dtype=np.float64)
    r = sigma * np.exp(np.log(np.clip(s, 1e-12, None)).mean(axis=1))
    return np.minimum(r, cap) if cap is not None else r
