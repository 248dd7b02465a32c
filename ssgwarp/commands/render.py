"""``ssgwarp render``: render a scene along its cameras or a smooth path (:mod:`ssgwarp.evaluation.render`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..capture.orbit import fit_splats, orbit_cameras, parse_up
from ..core.fileio import read_image, write_json
from ..core.imaging import VIDEO_FPS, VIDEO_SUFFIXES, mp4_writer_missing, write_video
from ..errors import InputError
from ..evaluation.render import log, smooth_path
from ..formats.registry import read_splat_file
from ..raster.environment import Environment
from ..raster.rendering import render_to_files
from ..services.runs import Run, claim_folder


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
