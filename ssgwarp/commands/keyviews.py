"""``ssgwarp keyviews``: choose key views and render their maps (:mod:`ssgwarp.stylization.keyviews`)."""
from __future__ import annotations

from pathlib import Path

from ..raster.groups import load_groups
from ..services.runs import Run, claim_folder
from ..stylization.keyviews import diffusion_size, parse_ids, render_keyviews, save_keyviews, select_keyviews


def add_arguments(parser) -> None:
    parser.add_argument("scene_dir", type=Path, help="a reconstruction run directory (scene.ply, cameras.json)")
    parser.add_argument("--keyviews", type=int, default=4, metavar="K", help="number of key views (default 4)")
    parser.add_argument("--ids", type=str, default=None,
                        help="comma-separated camera indices to use instead of automatic selection, e.g. 0,5,9")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default SCENE_DIR/keyviews)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing, non-empty --out")
    parser.add_argument("--max-side", type=int, default=512,
                        help="longer side of the diffusion resolution, a multiple of 8 (default 512)")
    parser.add_argument("--from-all", action="store_true",
                        help="choose among all cameras (default: among the training views)")


def run(args) -> int:
    scene_dir = Path(args.scene_dir)
    device = args.device
    scene, data = Run.reconstruction(scene_dir).load(device, load_images=False)  # key views are rendered: cameras suffice
    out = Path(args.out) if args.out is not None else scene_dir / "keyviews"
    classifier = None
    if (scene_dir / "groups" / "classifier.pt").is_file():
        classifier = load_groups(scene_dir, device).classifier
    cams = data.cameras
    cand = None if args.from_all or not getattr(data, "train_ids", None) else list(data.train_ids)
    ids = select_keyviews(cams, args.keyviews, parse_ids(args.ids), candidates=cand)
    size = diffusion_size(cams.width, cams.height, args.max_side)
    background = getattr(data, "background", None)
    kv = render_keyviews(scene, cams, ids, size, classifier, background=background)
    claim_folder(out, args.force)
    path = save_keyviews(kv, out)
    groups = f", {kv.num_groups} groups" if kv.groups is not None else ", no group classifier"
    print(f"key views {ids} ({', '.join(kv.cameras.names)}) at {size[0]}x{size[1]}{groups} -> {path.parent}")
    return 0
