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
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..capture.orbit import fit_splats, orbit_cameras, parse_up
from ..formats.registry import read_splat_file
from ..core.cameras import Cameras
from ..core.fileio import read_image, write_json
from ..core.imaging import VIDEO_FPS, VIDEO_SUFFIXES, mp4_writer_missing, write_video
from ..errors import InputError
from ..core.geometry import quat_to_rotmat, rotmat_to_quat
from ..raster.environment import Environment
from ..raster.rendering import render_to_files
from ..services.runs import Run, claim_folder

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


def add_arguments(parser) -> None:
    parser.add_argument("scene_dir", type=Path, metavar="RUN_OR_FILE",
                        help="a run folder: a reconstruction (scene.ply, cameras.json, data.json) or a stylize "
                             "output (its source reconstruction's cameras and split); or a splat file (PLY, "
                             "compressed PLY, SPZ, .splat) without a capture: cameras made around its splats")
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNGs")
    parser.add_argument("--path", type=int, nargs="?", const=120, default=None, metavar="N",
                        help="render N frames (default 120) along a smooth path through the cameras (a splat "
                             "file: around its orbit)")
    parser.add_argument("--split", choices=("train", "test", "all"), default="all",
                        help="which of the run's cameras to render (default all; with --path: the path's key cameras)")
    parser.add_argument("--open", action="store_true", help="with --path: an open path instead of a loop")
    parser.add_argument("--video", nargs="?", const="path.gif", default=None, metavar="FILE",
                        help="also write the frames as a looping video (default OUT/path.gif; a .mp4 name needs "
                             "imageio-ffmpeg; a relative name is inside --out)")
    parser.add_argument("--fps", type=int, default=VIDEO_FPS, help=f"--video's frames per second (default {VIDEO_FPS})")
    g = parser.add_argument_group("a splat file without its capture (cameras made around the splats)")
    g.add_argument("--views", type=int, default=24, help="orbit cameras without --path (default 24)")
    g.add_argument("--width", type=int, default=None,
                   help="image width (default: at most 512, and at most the width at which the median splat is one "
                        "pixel across)")
    g.add_argument("--up", default="auto",
                   help="the splats' up axis: auto (default: the thinnest principal axis of a layer of splats, else "
                        "the file's -y), an axis (+z, -y ...) or a vector x,y,z")
    parser.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true",
                        help="no progress bar (as the other commands' --quiet)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing, non-empty --out")


def _video_path(out: Path, video: Optional[str]) -> Optional[Path]:
    if video is None:
        return None
    p = Path(video).expanduser()
    p = p if p.is_absolute() else out / p
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"--video {video}: name a .gif or .mp4 file")
    if p.suffix.lower() == ".mp4" and mp4_writer_missing():
        raise InputError(f"--video {video}: {mp4_writer_missing()}")
    return p


def _file_cameras(args) -> tuple:
    """A splat file: ``(scene, cameras, record)`` with orbit cameras made around its splats."""
    scene = read_splat_file(args.scene_dir, args.device)
    if args.views < 1:
        raise InputError(f"--views must be >= 1, got {args.views}")
    fit = fit_splats(scene, up=parse_up(args.up), seed=args.seed)
    n = args.path if args.path is not None else args.views
    cams, rec = orbit_cameras(fit, n, width=args.width, names=[f"frame_{i:04d}" for i in range(n)]
                              if args.path is not None else None)
    if args.open:
        log.warning("--open: a splat file's path is its orbit, a loop")
    return scene, cams, {"source": str(args.scene_dir.resolve()), "fit": fit.record(), "cameras": rec}


def run(args) -> int:
    if args.path is not None and args.path < 1:
        raise InputError(f"--path must be >= 1, got {args.path}")
    if args.fps < 1:
        raise InputError(f"--fps must be >= 1, got {args.fps}")
    video = _video_path(args.out, args.video)
    if Path(args.scene_dir).expanduser().is_file():
        scene, cams, orbit = _file_cameras(args)
        background, env = [1.0, 1.0, 1.0], None
    else:
        run_ = Run.open(args.scene_dir)
        scene, data = run_.load(args.device, load_images=False)
        ids = data.split(args.split)
        if not ids:
            raise InputError(f"{args.scene_dir}: the run has no {args.split} cameras")
        cams, orbit = data.cameras[ids], None
        if args.path is not None:
            cams = smooth_path(cams, args.path, closed=not args.open)
        # (a stylized run: on its recorded, recoloured background)
        background = run_.background(data.background)
        env_path = Path(args.scene_dir) / "environment.json"   # the run's sky (reconstruct --sky), behind the splats
        env = Environment.load(env_path, device=args.device) if env_path.is_file() else None
    claim_folder(args.out, args.force)
    if args.path is not None:
        cams.to("cpu").save(args.out / "path_cameras.json")
    elif orbit is not None:
        cams.to("cpu").save(args.out / "cameras.json")
    if orbit is not None:
        write_json(args.out / "orbit.json", orbit)
    paths = render_to_files(scene, cams, args.out, background=background, progress=not args.quiet,
                            environment=env)
    said = f"{args.out}: {len(paths)} images"
    if orbit is not None:
        c = orbit["cameras"]
        said += f" at {c['width']}x{c['height']} on an orbit made around the splats (orbit.json)"
    if video is not None:
        frames = [(np.clip(read_image(p, 3), 0, 1) * 255 + 0.5).astype(np.uint8) for p in paths]
        write_video(video, frames, fps=args.fps)
        said += f"; video {video}"
    print(said)
    return 0
