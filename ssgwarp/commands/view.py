"""``ssgwarp view``: the pyvista viewer (:mod:`ssgwarp.viewer.app`)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import InputError
from ..viewer.app import COLOR_MODES, Viewer
from ..viewer.data import load_cameras, load_scene, resolve_groups, resolve_keyviews, resolve_ply, run_folders


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", type=Path,
                   help="a splat file (3DGS PLY, compressed PLY, SPZ, .splat) or a run directory with scene.ply: a "
                        "reconstruction or a stylize output (its source's cameras and groups, its key views)")
    p.add_argument("--color", "--colour", dest="color", choices=COLOR_MODES, default=None,
                   help="colouring: SH-DC colour, group label or opacity (default: group when the scene has "
                        "groups, else rgb)")
    p.add_argument("--cameras", type=Path, default=None,
                   help="cameras.json to draw as frustums (default: the run's, a stylized run's source's)")
    p.add_argument("--keyviews", nargs="+", default=None, metavar="VIEW",
                   help="key views to highlight: camera indices or names, or key-view JSON files/directories "
                        "(default: the run's keyviews/ when present, e.g. a stylize output's)")
    p.add_argument("--labels", type=Path, default=None,
                   help="per-Gaussian group ids (.npy, one int per Gaussian) instead of the grouping classifier")
    p.add_argument("--scene-dir", type=Path, default=None,
                   help="run directory whose cameras, groups/ and keyviews/ to use (default: the PLY's folder)")
    p.add_argument("--max-points", type=int, default=300_000,
                   help="point budget: above it a random subsample is drawn, and the viewer says so")
    p.add_argument("--glyphs", action="store_true", help="start with oriented ellipsoids instead of discs")
    p.add_argument("--max-glyphs", type=int, default=3000, help="Gaussians drawn as ellipsoids in glyph mode")
    p.add_argument("--sigma", type=float, default=1.0,
                   help="size of discs/ellipsoids in standard deviations of each Gaussian")
    p.add_argument("--opacity-threshold", type=float, default=0.0, help="hide Gaussians less opaque than this")
    p.add_argument("--frustum-size", type=float, default=None, help="camera frustum depth in world units")
    p.add_argument("--view", default=None, metavar="CAMERA", help="start looking through this camera (index or name)")
    p.add_argument("--render-view", default=None, metavar="CAMERA",
                   help="render this camera's splat image with the ssgwarp rasterizer and show it beside the cloud")
    p.add_argument("--render-width", type=int, default=320, help="width in pixels of the splat image")
    p.add_argument("--window-size", type=int, nargs=2, default=(1280, 800), metavar=("W", "H"),
                   help="window (and screenshot) size in pixels")
    p.add_argument("--no-legend", action="store_true", help="no group legend")
    p.add_argument("--screenshot", type=Path, default=None, metavar="PNG",
                   help="render off-screen to this PNG and exit (works with no display, see docs/viewer.md)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --screenshot file")


def run(args: argparse.Namespace) -> int:
    ply = resolve_ply(args.scene)
    scene_dir = args.scene_dir if args.scene_dir is not None else ply.parent
    if args.max_points is not None and args.max_points <= 0:
        raise InputError(f"--max-points must be positive, got {args.max_points}")
    if args.render_width <= 0:
        raise InputError(f"--render-width must be positive, got {args.render_width}")
    if args.screenshot is not None and args.screenshot.suffix.lower() not in (".png", ".jpg", ".jpeg", ".exr"):
        raise InputError(f"--screenshot {args.screenshot}: use a .png, .jpg or .exr file name")
    if args.screenshot is not None and args.screenshot.exists() and not getattr(args, "force", False):
        raise InputError(f"--screenshot {args.screenshot}: exists; pass --force to overwrite it")
    scene = load_scene(ply)
    found = run_folders(scene_dir)  # (a stylized run: its source's cameras and groups, its own key views)
    keyviews = args.keyviews
    if keyviews is None and found.keyviews is not None:
        keyviews = [str(found.keyviews)]
    cameras = load_cameras(args.cameras, found.cameras)
    try:
        keys = resolve_keyviews(keyviews or [], cameras)
    except InputError as e:
        if args.keyviews is not None:
            raise
        print(f"ssgwarp view: ignoring {keyviews[0]} ({e})", file=sys.stderr)
        keys = []
    groups = resolve_groups(scene, labels=args.labels, scene_dir=found.groups, device=args.device)
    color = args.color or ("group" if groups is not None else "rgb")
    viewer = Viewer(scene, groups=groups, cameras=cameras, keyviews=keys, color=color, max_points=args.max_points,
                    glyphs=args.glyphs, max_glyphs=args.max_glyphs, sigma=args.sigma,
                    opacity_threshold=args.opacity_threshold, frustum_size=args.frustum_size,
                    off_screen=args.screenshot is not None, window_size=tuple(args.window_size),
                    legend=not args.no_legend, render_width=args.render_width, device=args.device,
                    seed=args.seed, name=ply.name)
    try:
        if args.view is not None:
            viewer.select_camera(args.view)
            viewer.look_through()
        if args.render_view is not None:
            viewer.select_camera(args.render_view)
            viewer.show_splat()
            if args.view is None:  # the cloud's part of the window is narrower now: frame it again
                viewer._set_start_view()
        if args.screenshot is not None:
            viewer.screenshot(args.screenshot)
            print(f"wrote {args.screenshot}")
            return 0
        viewer.show()
    finally:
        viewer.close()
    return 0
