"""The embedded procedural scene and style image of ``ssgwarp demo`` (nothing is downloaded).

The scene (world z up, units of about a metre) is made of Gaussians with known
object ids:

====  ===========  ===========================================================
id    object       construction
====  ===========  ===========================================================
0     ground       a disc of flat Gaussians, two-tone checkerboard
1     red sphere   Fibonacci points on a sphere
2     blue box     a grid of points on the six faces of a cube, turned 30°
3     green torus  a (u, v) grid on a torus lying on the ground
4     yellow cone  rings on the side of an upright cone
====  ===========  ===========================================================

Colours carry a baked Lambertian shading (one sun plus ambient light) so the
objects look solid from every side while staying view-independent (an SH
degree 0 reconstruction can reproduce them). A ring of cameras at a fixed
elevation looks at the centre. :func:`render_views` renders it with
:func:`ssgwarp.rasterization`; :func:`write_transforms_dataset` writes a NeRF
``transforms.json`` capture (camera-to-world in OpenGL axes: x right, y up,
z back), which :func:`ssgwarp.capture.datasets.load_dataset` reads like any other.

:func:`style_image` paints the style: bold diagonal stripes and brush strokes
of saturated colours on a warm paper background.

Public API:
    SIZES                                       -> the demo sizes ("small", "default")
    build_scene(density, seed)                  -> ProceduralScene
    ring_cameras(n, width, height, ...)         -> Cameras (OpenCV axes, world-to-camera)
    render_views(scene, cameras, background)    -> (images [C,H,W,3], object ids [C,H,W])
    write_transforms_dataset(folder, images, cameras, ...) -> Path of transforms.json
    style_image(width, height, seed)            -> [H, W, 3] float32 numpy
    smooth_views(K, H, W, seed)                 -> smooth synthetic key views (rgb [K,H,W,3], depth [K,H,W])
    build_inside_out(density, seed)             -> ProceduralScene of an unbounded outdoor scene (below)
    rig_cameras(n, width, height, ...)          -> Cameras of an outward-looking rig (inside-out capture)
    surface_points(truth, n, seed)              -> n points of the truth's solid surfaces (a stand-in for SfM points)
    vary_exposures(src, dst, seed, ...)         -> a copy of a capture whose photos differ in exposure and tint

The inside-out scene (:func:`build_inside_out`, ids: 0 ground, 1 backdrop, 2 sky, 3 railing) is what a hand-held walk
on a rooftop sees: a textured ground disc of radius 6 around the rig, a ring of "buildings" (a cylinder
of radius 8 and height 3.5 with facades and windows) and a sky dome of radius 40 (a gradient with clouds).
:func:`rig_cameras` looks outward from a small circle at its centre, so nothing the views show lies near
the point their optical axes meet (behind them): the capture that defeats a bounded random initialisation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from .core.cameras import Cameras, intrinsics, look_at
from .errors import InputError
from .core.fileio import write_image, write_json
from .raster.scene import GaussianScene, rgb_to_sh_dc, sh_dc_to_rgb

OBJECT_NAMES = ("ground", "red sphere", "blue box", "green torus", "yellow cone")
BACKGROUND = (1.0, 1.0, 1.0)
# the OpenCV camera axes (x right, y down, z forward) -> OpenGL (x right, y up, z back) and back
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class DemoSize:
    """One demo size: the capture (views, width x height) and the work done on it."""

    views: int
    width: int
    height: int
    density: float            # multiplies the number of ground-truth Gaussians
    reconstruct_iters: int
    init_points: int          # random initial points of the reconstruction
    max_gaussians: int
    group_iters: int
    keyviews: int
    max_side: int             # key-view (diffusion) resolution, longer side
    stylize_iters: int
    stylize_lr: float
    path_frames: int
    eval_pairs: int
    group_dim: int = 16       # identity length of the groups trained with the reconstruction


SIZES: dict[str, DemoSize] = {
    "small": DemoSize(views=8, width=48, height=36, density=0.5, reconstruct_iters=150, init_points=600,
                      max_gaussians=2500, group_iters=40, keyviews=2, max_side=48, stylize_iters=20,
                      stylize_lr=0.05, path_frames=0, eval_pairs=4),
    "default": DemoSize(views=24, width=80, height=60, density=1.0, reconstruct_iters=700, init_points=2000,
                        max_gaussians=5000, group_iters=150, keyviews=4, max_side=80, stylize_iters=40,
                        stylize_lr=0.05, path_frames=0, eval_pairs=4, group_dim=8),
}


@dataclass
class ProceduralScene:
    """The ground truth: ``scene`` (SH degree 0, no identities), ``object_ids [N]`` (index into ``names``)."""

    scene: GaussianScene
    object_ids: torch.Tensor
    names: tuple[str, ...] = OBJECT_NAMES

    def __len__(self) -> int:
        return len(self.scene)

    def counts(self) -> dict[str, int]:
        c = torch.bincount(self.object_ids, minlength=len(self.names)).tolist()
        return {n: int(k) for n, k in zip(self.names, c)}


# ----------------------------------------------------------------------------- geometry
def _shade(base: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Baked Lambert shading: ``base [N,3] * (ambient + diffuse * max(0, n . sun))``."""
    sun = np.array([0.45, -0.35, 0.82])
    sun /= np.linalg.norm(sun)
    lam = np.clip(normals @ sun, 0.0, 1.0)
    return np.clip(base * (0.45 + 0.6 * lam)[:, None], 0.0, 1.0)


def _frame(normals: np.ndarray) -> np.ndarray:
    """``[N, 4]`` wxyz quaternions rotating +z onto each unit normal (so flat Gaussians lie on the surface)."""
    z = np.array([0.0, 0.0, 1.0])
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.cross(np.broadcast_to(z, n.shape), n)
    s = np.linalg.norm(axis, axis=1)
    c = n @ z
    ang = np.arctan2(s, c)
    axis = np.where(s[:, None] > 1e-9, axis / np.maximum(s, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
    q = np.concatenate([np.cos(ang / 2)[:, None], axis * np.sin(ang / 2)[:, None]], axis=1)
    return q


def _sphere(n: int, centre, radius: float):
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = math.pi * (1 + 5 ** 0.5) * i
    nrm = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    return np.asarray(centre) + radius * nrm, nrm


def _box(per_side: int, centre, half: float, yaw: float):
    g = (np.arange(per_side) + 0.5) / per_side * 2 - 1
    u, v = np.meshgrid(g, g, indexing="ij")
    u, v = u.ravel(), v.ravel()
    pts, nrm = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((u.size, 3))
            others = [a for a in range(3) if a != axis]
            p[:, axis] = sign
            p[:, others[0]], p[:, others[1]] = u, v
            nn = np.zeros((u.size, 3))
            nn[:, axis] = sign
            pts.append(p)
            nrm.append(nn)
    pts, nrm = np.concatenate(pts) * half, np.concatenate(nrm)
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return pts @ R.T + np.asarray(centre), nrm @ R.T


def _torus(nu: int, nv: int, centre, major: float, minor: float):
    u, v = np.meshgrid(np.arange(nu) / nu * 2 * math.pi, np.arange(nv) / nv * 2 * math.pi, indexing="ij")
    u, v = u.ravel(), v.ravel()
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    ring = np.stack([np.cos(u), np.sin(u), np.zeros_like(u)], 1) * major
    return np.asarray(centre) + ring + minor * nrm, nrm


def _cone(rings: int, per_ring: int, centre, radius: float, height: float):
    t = (np.arange(rings) + 0.5) / rings                      # 0 at the base, 1 at the tip
    a = np.arange(per_ring) / per_ring * 2 * math.pi
    T, A = np.meshgrid(t, a, indexing="ij")
    T, A = T.ravel(), A.ravel()
    keep = np.random.default_rng(0).random(T.size) < (1 - T) + 0.15  # thinner towards the tip
    T, A = T[keep], A[keep]
    r = radius * (1 - T)
    pts = np.stack([r * np.cos(A), r * np.sin(A), height * T], 1) + np.asarray(centre)
    slope = radius / height
    nrm = np.stack([np.cos(A), np.sin(A), np.full_like(A, slope)], 1)
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def build_scene(density: float = 1.0, seed: int = 0) -> ProceduralScene:
    """The ground-truth Gaussians (see the module docstring); ``density`` scales their number (~3000 at 1)."""
    if not density > 0:
        raise InputError(f"procedural scene: density must be > 0, got {density}")
    rng = np.random.default_rng(seed)
    d = math.sqrt(density)
    parts = []   # (xyz, normals, base rgb, spacing, thickness, object id)

    # ground: a disc of radius 2.2, checkerboard of 0.5 m squares
    step = 0.11 / d
    g = np.arange(-2.2, 2.2 + 1e-9, step)
    X, Y = np.meshgrid(g, g, indexing="ij")
    X, Y = X.ravel(), Y.ravel()
    keep = X ** 2 + Y ** 2 <= 2.2 ** 2
    X, Y = X[keep] + rng.normal(0, step * 0.1, keep.sum()), Y[keep] + rng.normal(0, step * 0.1, keep.sum())
    xyz = np.stack([X, Y, np.zeros_like(X)], 1)
    check = ((np.floor(X / 0.5) + np.floor(Y / 0.5)) % 2).astype(bool)
    base = np.where(check[:, None], [0.80, 0.76, 0.66], [0.55, 0.52, 0.47])
    parts.append((xyz, np.tile([0.0, 0.0, 1.0], (len(X), 1)), base, step * 0.75, 0.01, 0))

    xyz, nrm = _sphere(max(60, int(420 * density)), (-0.75, -0.45, 0.5), 0.5)
    parts.append((xyz, nrm, np.array([0.88, 0.16, 0.12]), 0.075 / d, 0.02, 1))

    xyz, nrm = _box(max(5, int(round(9 * d))), (0.8, -0.5, 0.36), 0.36, math.radians(30))
    parts.append((xyz, nrm, np.array([0.15, 0.32, 0.85]), 0.06 / d, 0.015, 2))

    xyz, nrm = _torus(max(16, int(36 * d)), max(8, int(14 * d)), (0.2, 0.85, 0.16), 0.45, 0.16)
    parts.append((xyz, nrm, np.array([0.18, 0.72, 0.25]), 0.055 / d, 0.02, 3))

    xyz, nrm = _cone(max(6, int(12 * d)), max(14, int(30 * d)), (-0.95, 0.75, 0.0), 0.32, 0.85)
    parts.append((xyz, nrm, np.array([0.95, 0.78, 0.12]), 0.06 / d, 0.02, 4))

    means, quats, scales, rgbs, ids = [], [], [], [], []
    for xyz, nrm, base, spacing, thick, oid in parts:
        n = len(xyz)
        base = np.broadcast_to(np.asarray(base, dtype=np.float64), (n, 3))
        col = _shade(base, nrm) * (1.0 + rng.normal(0, 0.03, (n, 1)))
        means.append(xyz)
        quats.append(_frame(nrm))
        scales.append(np.tile([spacing, spacing, thick], (n, 1)))
        rgbs.append(np.clip(col, 0.0, 1.0))
        ids.append(np.full(n, oid))
    t = lambda a: torch.from_numpy(np.concatenate(a)).float()  # noqa: E731
    rgb = t(rgbs)
    n = rgb.shape[0]
    scene = GaussianScene(t(means), torch.log(t(scales)), t(quats), torch.full((n,), 4.0), rgb_to_sh_dc(rgb))
    return ProceduralScene(scene, torch.from_numpy(np.concatenate(ids)).long())


def ring_cameras(n: int, width: int, height: int, *, radius: float = 4.2, elevation_deg: float = 28.0,
                 fov_x_deg: float = 55.0, target: Sequence[float] = (0.0, 0.0, 0.35),
                 names: Optional[Sequence[str]] = None) -> Cameras:
    """``n`` cameras evenly spaced on a circle around the z axis, looking at ``target`` (OpenCV axes)."""
    if n < 1 or width < 1 or height < 1:
        raise InputError(f"ring_cameras: need n >= 1 and a positive size, got n={n}, {width}x{height}")
    a = torch.arange(n, dtype=torch.float64) / n * 2 * math.pi
    el = math.radians(elevation_deg)
    eyes = torch.stack([radius * math.cos(el) * torch.cos(a), radius * math.cos(el) * torch.sin(a),
                        torch.full_like(a, radius * math.sin(el))], 1)
    tgt = torch.tensor(target, dtype=torch.float64).expand(n, 3)
    vm = look_at(eyes + tgt, tgt, up=(0.0, 0.0, 1.0))
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = intrinsics(f, f, width / 2.0, height / 2.0, n)
    return Cameras(vm.float(), K, width, height, list(names) if names else [f"r_{i:03d}" for i in range(n)])


@torch.no_grad()
def render_views(gt: ProceduralScene, cameras: Cameras,
                 background: Sequence[float] = BACKGROUND) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the ground truth: ``(images [C,H,W,3] in [0,1], object ids [C,H,W] long, -1 = background)``.

    Colour and a one-hot of the object ids go through one pass of the rasterizer.
    """
    scene = gt.scene
    k = len(gt.names)
    onehot = torch.nn.functional.one_hot(gt.object_ids, k).to(scene.dtype)
    bg = torch.zeros(len(cameras), 3 + k, dtype=scene.dtype, device=scene.device)
    bg[:, :3] = torch.tensor(background, dtype=scene.dtype, device=scene.device)
    out, alpha, _ = scene.render(cameras.to(scene.device), extra=onehot, backgrounds=bg)
    images = out[..., :3].clamp(0.0, 1.0)
    ids = out[..., 3:].argmax(dim=-1)
    ids[alpha[..., 0] < 0.5] = -1
    return images, ids


def write_transforms_dataset(folder: str | Path, images: torch.Tensor, cameras: Cameras) -> Path:
    """Write ``images [C,H,W,3]`` and ``cameras`` as a NeRF capture: ``folder/images/*.png`` + ``transforms.json``.

    ``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z back),
    with ``fl_x fl_y cx cy w h`` and ``camera_angle_x``. Returns the JSON's path.
    """
    folder = Path(folder)
    C, H, W = images.shape[:3]
    if C != len(cameras) or (W, H) != (cameras.width, cameras.height):
        raise InputError(f"write_transforms_dataset: {C} images of {W}x{H} for {len(cameras)} cameras of "
                         f"{cameras.width}x{cameras.height}")
    c2w = cameras.camtoworlds.double().cpu().numpy() @ _CV_TO_GL
    K = cameras.Ks[0].double().cpu()
    frames = []
    for i, name in enumerate(cameras.names):
        rel = f"images/{name}.png"
        write_image(folder / rel, images[i])
        frames.append({"file_path": rel, "transform_matrix": c2w[i].tolist()})
    meta = {"camera_angle_x": 2.0 * math.atan(W / (2.0 * float(K[0, 0]))),
            "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "w": int(W), "h": int(H), "frames": frames}
    path = folder / "transforms.json"
    write_json(path, meta)
    return path


def style_image(width: int = 192, height: int = 192, seed: int = 0) -> np.ndarray:
    """``[H, W, 3]`` float32: bold strokes of saturated colours over diagonal stripes on warm paper."""
    if width < 8 or height < 8:
        raise InputError(f"style_image: size {width}x{height} too small (>= 8x8)")
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    img = np.empty((height, width, 3))
    img[:] = (0.96, 0.90, 0.74)                                  # paper
    colours = np.array([[0.86, 0.10, 0.12], [0.05, 0.22, 0.70], [0.98, 0.76, 0.05],
                        [0.05, 0.55, 0.35], [0.10, 0.08, 0.10], [0.95, 0.45, 0.10]])
    # diagonal stripes, two colours alternating with paper
    period = max(6.0, width / 7.0)
    band = np.floor((xx + yy) / period).astype(int)
    stripe = ((xx + yy) % period) < period * 0.45
    for c in (0, 1):
        m = stripe & (band % 4 == 2 * c)
        img[m] = colours[c]
    # brush strokes: thick sinuous lines with a dark edge
    for s in range(9):
        col = colours[rng.integers(0, len(colours))]
        x0, y0 = rng.uniform(0, width), rng.uniform(0, height)
        ang = rng.uniform(0, math.pi)
        length = rng.uniform(0.4, 0.9) * max(width, height)
        thick = rng.uniform(0.03, 0.07) * min(width, height)
        t = np.linspace(-0.5, 0.5, 200)[:, None]
        wob = 0.08 * length * np.sin(t * rng.uniform(4, 9) + rng.uniform(0, 6))
        px = x0 + t * length * math.cos(ang) - wob * math.sin(ang)
        py = y0 + t * length * math.sin(ang) + wob * math.cos(ang)
        # distance of every pixel to the polyline's sample points (coarse but fine at these sizes)
        d = np.full((height, width), np.inf)
        for k in range(0, 200, 4):
            d = np.minimum(d, np.hypot(xx - px[k, 0], yy - py[k, 0]))
        img[(d < thick) & (d >= thick * 0.75)] = colours[4] if s % 3 else col * 0.5
        img[d < thick * 0.75] = col
    return np.clip(img, 0.0, 1.0).astype(np.float32)


__all__ = ["SIZES", "DemoSize", "OBJECT_NAMES", "BACKGROUND", "ProceduralScene", "build_scene", "ring_cameras",
           "render_views", "write_transforms_dataset", "style_image", "INSIDE_OUT_NAMES", "build_inside_out",
           "surface_points", "rig_cameras", "vary_exposures"]


def smooth_views(K: int, H: int, W: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``K`` smooth synthetic key views for Stage 1 runs without a scene (tests, benchmarks): ``rgb
    [K, H, W, 3]`` in [0.1, 0.9], sine gradients with a random phase per view and channel, and
    ``depth [K, H, W]`` >= 1, a ramp that steepens from view to view."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    ph = torch.rand(K, 3, generator=g) * 6
    rgb = 0.5 + 0.4 * torch.sin(3 * xx[None, ..., None] + 2 * yy[None, ..., None] + ph[:, None, None, :])
    depth = 1.0 + xx[None] + 0.5 * yy[None] * torch.arange(1, K + 1).view(K, 1, 1)
    return rgb.float(), depth.float()


# ----------------------------------------------------------------------------- inside-out scene
INSIDE_OUT_NAMES = ("ground", "backdrop", "sky", "railing")


def _ring_normals_up(n: int) -> np.ndarray:
    return np.tile([0.0, 0.0, 1.0], (n, 1))


def build_inside_out(density: float = 1.0, seed: int = 0, railing: bool = False) -> ProceduralScene:
    """The inside-out ground truth (see the module docstring); about 24,000 Gaussians at ``density`` 1.
    ``railing``: add near structure (id 3), a railing around the rig at radius 2.5 (posts every 15 degrees,
    a top rail at 1.1 m and a middle one at 0.55 m, dark green metal): what a rooftop walk sees close by."""
    if not density > 0:
        raise InputError(f"procedural scene: density must be > 0, got {density}")
    rng = np.random.default_rng(seed)
    d = math.sqrt(density)
    parts = []   # (xyz, normals, rgb, spacing, thickness, id)

    # ground: disc of radius 6.2, 1 m tiles in two tones with a darker grout
    step = 0.15 / d
    g = np.arange(-6.2, 6.2 + 1e-9, step)
    X, Y = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    keep = X ** 2 + Y ** 2 <= 6.2 ** 2
    X, Y = X[keep], Y[keep]
    tile = ((np.floor(X) + np.floor(Y)) % 2).astype(bool)
    rgb = np.where(tile[:, None], [0.62, 0.58, 0.52], [0.42, 0.40, 0.38])
    grout = (np.abs(X - np.round(X)) < 0.06) | (np.abs(Y - np.round(Y)) < 0.06)
    rgb[grout] = [0.25, 0.24, 0.23]
    parts.append((np.stack([X, Y, np.zeros_like(X)], 1), _ring_normals_up(len(X)), rgb, step, 0.01, 0))

    # backdrop: facades on a cylinder of radius 8 (normals inward), one colour per 20-degree block, windows
    r, top = 8.0, 3.5
    da = (0.12 / d) / r
    a = np.arange(0.0, 2 * math.pi, da)
    z = np.arange(0.06, top, 0.12 / d)
    A, Z = (t.ravel() for t in np.meshgrid(a, z, indexing="ij"))
    palette = np.array([[0.80, 0.42, 0.30], [0.85, 0.80, 0.65], [0.45, 0.55, 0.70], [0.70, 0.70, 0.72],
                        [0.55, 0.35, 0.30], [0.90, 0.70, 0.40]])
    block = np.floor(A / math.radians(20.0)).astype(int)
    rgb = palette[rng.permutation(len(palette))[block % len(palette)]].astype(np.float64)
    u = (A * r) % 1.0
    v = Z % 0.9
    window = (u > 0.3) & (u < 0.7) & (v > 0.3) & (v < 0.7)
    rgb[window] = [0.12, 0.16, 0.22]
    rgb *= (1.0 + rng.normal(0, 0.03, (len(A), 1)))
    xyz = np.stack([r * np.cos(A), r * np.sin(A), Z], 1)
    nrm = -np.stack([np.cos(A), np.sin(A), np.zeros_like(A)], 1)
    parts.append((xyz, nrm, rgb, 0.12 / d, 0.02, 1))

    # sky: a dome of radius 40 (elevation -5..90 degrees), horizon haze to zenith blue, with clouds
    R = 40.0
    n = max(500, int(7000 * density))
    i = np.arange(n) + 0.5
    zz = np.sin(math.radians(-5.0)) + (1 - np.sin(math.radians(-5.0))) * i / n   # uniform in z: uniform area
    ph = math.pi * (1 + 5 ** 0.5) * i
    rho = np.sqrt(1 - zz ** 2)
    dirs = np.stack([rho * np.cos(ph), rho * np.sin(ph), zz], 1)
    t = np.clip(zz, 0.0, 1.0)[:, None] ** 0.6
    rgb = (1 - t) * np.array([0.85, 0.90, 0.95]) + t * np.array([0.30, 0.50, 0.85])
    cloud = (np.sin(3.0 * ph * 0.013 + 2 * zz) * np.cos(7.0 * zz + np.cos(ph * 0.007)) > 0.55) & (zz > 0.1)
    rgb[cloud] = [0.97, 0.97, 0.98]
    spacing = R * math.sqrt(2 * math.pi * (1 - math.sin(math.radians(-5.0))) / n)
    parts.append((R * dirs, -dirs, rgb, spacing, spacing * 0.2, 2))

    if railing:
        rr, thick = 2.5, 0.03
        metal = np.array([0.20, 0.32, 0.26])
        for zr in (1.1, 0.55):   # rails: rings of small round Gaussians
            a = np.arange(0.0, 2 * math.pi, (0.02 / d) / rr)
            xyz = np.stack([rr * np.cos(a), rr * np.sin(a), np.full_like(a, zr)], 1)
            nrm = -np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
            shade = np.clip(0.8 + 0.2 * np.sin(3 * a)[:, None], 0, 1)
            parts.append((xyz, nrm, metal * shade * 1.15, 0.02 / d, thick, 3))
        for a0 in np.arange(0.0, 2 * math.pi, math.radians(15.0)):   # posts
            z = np.arange(0.0, 1.1, 0.02 / d)
            xyz = np.stack([np.full_like(z, rr * math.cos(a0)), np.full_like(z, rr * math.sin(a0)), z], 1)
            nrm = np.tile([-math.cos(a0), -math.sin(a0), 0.0], (len(z), 1))
            parts.append((xyz, nrm, np.tile(metal, (len(z), 1)), 0.02 / d, thick, 3))

    means, quats, scales, rgbs, ids = [], [], [], [], []
    for xyz, nrm, col, sp, thick, oid in parts:
        m = len(xyz)
        means.append(xyz)
        quats.append(_frame(nrm))
        scales.append(np.tile([sp * 0.75, sp * 0.75, thick], (m, 1)))
        rgbs.append(np.clip(col, 0.0, 1.0))
        ids.append(np.full(m, oid))
    cat = lambda x: torch.from_numpy(np.concatenate(x)).float()  # noqa: E731
    rgb = cat(rgbs)
    scene = GaussianScene(cat(means), torch.log(cat(scales)), cat(quats), torch.full((len(rgb),), 4.0),
                          rgb_to_sh_dc(rgb))
    return ProceduralScene(scene, torch.from_numpy(np.concatenate(ids)).long(), INSIDE_OUT_NAMES)


def surface_points(truth: ProceduralScene, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(xyz [n, 3], rgb [n, 3])``: ``n`` centres of ``truth``'s Gaussians (seeded) with their colours, none of the
    sky: a stand-in for the sparse points structure from motion gives of a real capture (the solid surfaces)."""
    solid = torch.nonzero(truth.object_ids != truth.names.index("sky"))[:, 0] if "sky" in truth.names \
        else torch.arange(len(truth))
    pick = solid[torch.randperm(len(solid), generator=torch.Generator().manual_seed(seed))[:n]]
    return truth.scene.means[pick].float(), sh_dc_to_rgb(truth.scene.sh_dc[pick]).clamp(0.0, 1.0).float()


def rig_cameras(n: int, width: int, height: int, *, radius: float = 0.3, eye_height: float = 1.5,
                pitch_deg: float = 5.0, fov_x_deg: float = 70.0, turns: float = 1.0,
                names: Optional[Sequence[str]] = None) -> Cameras:
    """``n`` cameras on a circle of ``radius`` at ``eye_height``, each looking outward (away from the circle's
    centre) and ``pitch_deg`` up, their headings spread over ``turns`` full turns (OpenCV axes)."""
    if n < 1 or width < 1 or height < 1:
        raise InputError(f"rig_cameras: need n >= 1 and a positive size, got n={n}, {width}x{height}")
    a = torch.arange(n, dtype=torch.float64) / n * 2 * math.pi * turns
    eyes = torch.stack([radius * torch.cos(a), radius * torch.sin(a), torch.full_like(a, eye_height)], 1)
    p = math.radians(pitch_deg)
    look = torch.stack([math.cos(p) * torch.cos(a), math.cos(p) * torch.sin(a), torch.full_like(a, math.sin(p))], 1)
    vm = look_at(eyes, eyes + look, up=(0.0, 0.0, 1.0))
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = intrinsics(f, f, width / 2.0, height / 2.0, n)
    return Cameras(vm.float(), K, width, height, list(names) if names else [f"o_{i:03d}" for i in range(n)])


# ----------------------------------------------------------------------------- photos that differ in exposure
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def vary_exposures(src: str | Path, dst: str | Path, *, seed: int = 0, gain: tuple[float, float] = (0.6, 1.4),
                   tint: float = 0.1, names: Optional[Sequence[str]] = None) -> dict[str, list[float]]:
    """Copy the capture folder ``src`` to ``dst`` (which must not exist) with each photo's exposure and white
    balance changed, as a camera's auto-exposure would: its RGB times a gain drawn uniformly in ``gain``,
    times a tint of ``1 +- tint`` per channel (uniform), 8-bit, clipped; alpha (RGBA) unchanged. Photos are
    the PNG/JPEG files under ``src`` (in sorted path order, one seeded draw each); ``names`` (paths relative to
    ``src``) limits the change to those. Everything else is copied as is. Returns ``{relative path: [r, g, b]
    factors}`` of the changed photos. The test capture of ``reconstruct --appearance`` (docs/reconstruction.md)."""
    import shutil

    from .core.fileio import read_image

    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(f"{src}: not a capture folder")
    if dst.exists():
        raise InputError(f"{dst}: exists; vary_exposures writes a new folder")
    lo, hi = float(gain[0]), float(gain[1])
    if not 0 < lo <= hi or not 0 <= tint < 1:
        raise InputError(f"vary_exposures: need 0 < gain[0] <= gain[1] and 0 <= tint < 1, got {gain}, {tint}")
    shutil.copytree(src, dst)
    rng = np.random.default_rng(seed)
    wanted = None if names is None else {Path(n).as_posix() for n in names}
    factors: dict[str, list[float]] = {}
    for path in sorted(p for p in dst.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()):
        rel = path.relative_to(dst).as_posix()
        g = rng.uniform(lo, hi) * (1.0 + rng.uniform(-tint, tint, 3))
        if wanted is not None and rel not in wanted:
            continue
        img = read_image(path)
        img[..., :3] = img[..., :3] * g.astype(np.float32)
        path.unlink()
        write_image(path, img)
        factors[rel] = [round(float(v), 6) for v in g]
    return factors
