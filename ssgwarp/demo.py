"""``ssgwarp demo``: the whole pipeline on an embedded procedural scene, with nothing to download.

Stages (each through its module's Python API, all under ``OUT``):

1. **data** — :mod:`ssgwarp.procedural` builds five objects on a ground plane as
   Gaussians with known ids, renders them from a ring of cameras with
   :func:`ssgwarp.rasterization` and writes a NeRF capture ``OUT/data``
   (``transforms.json`` + ``images/``) and a style image ``OUT/style.png``.
2. **reconstruct** — 3DGS from random initial points (:mod:`ssgwarp.reconstruction.reconstruct`) → ``OUT/scene``;
   without Segment Anything weights, with Gaussian Grouping on mask-free clusters trained in the same loop
   (``reconstruct --groups``, :mod:`ssgwarp.grouping.joint`) → ``OUT/scene/groups``.
3. **group** — with Segment Anything's weights on this machine: its instances associated across views
   (:mod:`ssgwarp.grouping.segment`) and Gaussian Grouping on them (:mod:`ssgwarp.grouping.stage`) →
   ``OUT/scene/groups``; the summary says which kind of groups ran (``group_kind``). The group maps are
   scored against the true object ids.
4. **stylize** — key views, Stage 1 (diffusion; skipped when its weights are not on
   this machine, and the summary says so: the demo downloads nothing, ``ssgwarp weights
   --download stage1`` fetches them) and Stage 2 (:mod:`ssgwarp.stylization.stylize`) → ``OUT/stylized``.
5. **evaluate** — consistency, style/content losses and PSNR (:mod:`ssgwarp.evaluation.evaluate`)
   of the reconstruction and of the stylized scene → ``OUT/evaluation.md``.
6. **sheet** — ``OUT/contact_sheet.png``: captured | reconstructed | groups | stylized, and the style.

``OUT/summary.json`` holds the printed summary; ``OUT/demo.json`` the finished
stages (``--resume`` skips them after a Ctrl-C). Existing outputs are never
overwritten without ``--force``.
"""
from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import torch

from . import procedural as P
from .services import weights as W
from .capture.datasets import load_dataset
from .stylization.diffusion_models import WEIGHT_KEYS
from .errors import InputError
from .evaluation.evaluate import EvalOptions, evaluate_run, load_models
from .evaluation.table import comparison_table
from .core.fileio import atomic_path, read_image, write_image, write_json
from .grouping.joint import reconstruct_with_groups
from .grouping.stage import group_scene
from .grouping.model import GroupConfig
from .raster.groups import load_groups
from .raster.groups import render_group_maps
from .grouping.segment import make_masks
from .core.palette import colorize_labels
from .formats.ply import read_ply
from .procedural import SIZES
from .reconstruction.reconstruct import ReconstructConfig, reconstruct
from .reconstruction.recipe import Recipe
from .reconstruction.strategy import DefaultStrategy
from .services.runs import Run, claim, resume_record, resumed_stages
from .stylization.stylize import StylizeOptions, stylize_run
from .stylization.stage2 import Stage2Config

OUTPUTS = ("demo.json", "data", "style.png", "scene", "stylized", "evaluation.md", "contact_sheet.png",
           "summary.json")
STAGES = ("data", "reconstruct", "group", "stylize", "evaluate", "sheet")
FORMAT = "ssgwarp-demo/1"
OFFLINE_REASON = "ssgwarp demo downloads nothing"
# the share of the reconstruction after which its Gaussians are clustered and the groups trained (densification
# stops at half of it: the clusters are taken from a scene that had time to settle; a grouping step costs about
# 1.5x a plain one, and 0.8 gave the same groups and distances as 0.7 at seeds 0-2, 2026-11-28)
GROUP_START = 0.8


# ----------------------------------------------------------------------------- helpers
def _resolve_device(device) -> torch.device:
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _size(size) -> tuple[str, "object"]:
    if not isinstance(size, str):
        return "custom", size
    if size not in SIZES:
        raise InputError(f"--size {size}: use one of {', '.join(SIZES)}")
    return size, SIZES[size]


def _prepare_out(out: Path, force: bool, resume: bool, record: dict) -> dict:
    """Claim ``out`` (:func:`ssgwarp.services.runs.claim`: never overwritten without ``force``); returns the
    stage record to continue (``resume``: the finished stages of the same options)."""
    claimed = claim(out, OUTPUTS, force=force, resume=resume, what="a demo run")
    if claimed.existing and resume:
        record["stages"] = resumed_stages(claimed, "demo.json", "options", resume_record(**record["options"]),
                                          "the earlier demo", kind="a demo record", fmt=FORMAT, required=True)
        return record
    claimed.clear()   # --force: remove only what the demo writes
    return record


def _weights_missing() -> list[str]:
    """Stage 1 weight keys not found on this machine (no import of diffusers)."""
    return [k for k in WEIGHT_KEYS if W.find(k) is None]


def group_agreement(labels: torch.Tensor, objects: torch.Tensor, num_objects: int) -> dict:
    """How well group maps ``labels [C,H,W]`` match the true object maps ``objects [C,H,W]`` (-1: background).

    Over the pixels an object covers: ``purity`` = share of pixels whose group's majority
    object is their own object; ``separated`` = objects whose majority group no other
    object shares (the ground counts as an object).
    """
    lab = labels.reshape(-1).cpu().long()
    obj = objects.reshape(-1).cpu().long()
    keep = obj >= 0
    lab, obj = lab[keep], obj[keep]
    if lab.numel() == 0:
        return {"purity": None, "separated": 0, "objects": num_objects, "pixels": 0}
    k = int(lab.max()) + 1
    table = torch.zeros(k, num_objects, dtype=torch.long)
    table.index_put_((lab, obj), torch.ones_like(lab), accumulate=True)
    purity = float(table.max(dim=1).values.sum()) / float(table.sum())
    major = table.argmax(dim=0)                                    # the majority group of each object
    present = table.sum(dim=0) > 0
    sep = sum(1 for o in range(num_objects) if present[o]
              and all(major[o] != major[p] for p in range(num_objects) if p != o and present[p]))
    return {"purity": purity, "separated": int(sep), "objects": int(present.sum()), "pixels": int(table.sum()),
            "majority_group": {int(o): int(major[o]) for o in range(num_objects) if present[o]}}


def _contact_sheet(path: Path, rows: list[dict], style, title: str, groups_kind: str = "mask-free clusters") -> Path:
    """Rows of captured | reconstruction | groups | stylized, the style image on the right (a matplotlib
    Figure drawn by Agg: no pyplot, the process's backend untouched)."""
    # (matplotlib is imported here: it costs ~0.3 s at start-up and only the sheet needs it)
    from matplotlib.figure import Figure
    from matplotlib.gridspec import GridSpec

    cols = ("captured", "reconstruction", f"groups ({groups_kind})", "stylized")
    n = len(rows)
    h, w = rows[0]["captured"].shape[:2]
    cell = 2.4
    fig = Figure(figsize=(cell * 5.2, n * cell * h / w + 0.9), dpi=110)
    gs = GridSpec(n, 5, figure=fig, wspace=0.04, hspace=0.16)
    for i, r in enumerate(rows):
        for j, key in enumerate(("captured", "reconstruction", "groups", "stylized")):
            ax = fig.add_subplot(gs[i, j])
            ax.imshow(r[key].detach().float().clamp(0, 1).cpu().numpy(), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=9)
            if j == 0:
                ax.set_ylabel(r["label"], fontsize=8)
    ax = fig.add_subplot(gs[:, 4])
    ax.imshow(style.detach().float().clamp(0, 1).cpu().numpy())
    ax.set_title("style", fontsize=9)
    ax.axis("off")
    fig.suptitle(title, fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return path


def _fmt(x, spec: str = ".4g", none: str = "n/a") -> str:
    return none if x is None else format(x, spec)


# ----------------------------------------------------------------------------- the demo
class _Demo:
    """One demo run's context: the folder, the size, the stage record and how to speak."""

    def __init__(self, out: Path, name: str, sz, device: torch.device, seed: int, progress: bool, say, record: dict):
        self.out, self.name, self.sz, self.device, self.seed, self.progress, self.say = \
            out, name, sz, device, int(seed), progress, say
        self.record = record
        self.stages: dict = record["stages"]
        self.times: dict[str, float] = {}
        self.data_dir, self.scene_dir, self.styl_dir = out / "data", out / "scene", out / "stylized"

    def todo(self, stage: str) -> bool:
        return not self.stages.get(stage, {}).get("done")

    def done(self, stage: str, **info) -> None:
        self.stages[stage] = {"done": True, **info}
        write_json(self.out / "demo.json", self.record)

    def header(self, i: int, stage: str, what: str) -> None:
        self.say(f"[{i}/{len(STAGES)}] {stage}: {what}")


def _stage_data(d: _Demo):
    """1: the procedural capture and the style image; returns the true scene, cameras, images, object maps."""
    sz = d.sz
    gt = P.build_scene(sz.density, seed=d.seed)
    cams = P.ring_cameras(sz.views, sz.width, sz.height)
    d.header(1, "data", f"procedural scene ({len(gt)} Gaussians, objects: {', '.join(gt.names)}), "
                        f"{sz.views} views {sz.width}x{sz.height}")
    t0 = time.perf_counter()
    gt_dev = P.ProceduralScene(gt.scene.to(d.device), gt.object_ids.to(d.device), gt.names)
    images, objects = P.render_views(gt_dev, cams.to(d.device))
    if d.todo("data"):
        P.write_transforms_dataset(d.data_dir, images.cpu(), cams)
        write_image(d.out / "style.png", P.style_image(192, 192, seed=d.seed))
        d.done("data", seconds=time.perf_counter() - t0)
    d.times["data"] = d.stages["data"]["seconds"]
    return gt, cams, images, objects


def _stage_reconstruct(d: _Demo, joint: bool) -> dict:
    """2: 3DGS; ``joint``: with Gaussian Grouping on mask-free clusters in the same loop."""
    sz = d.sz
    d.header(2, "reconstruct", f"3DGS from {sz.init_points} random points, {sz.reconstruct_iters} steps, "
                               f"SH degree 0 (the colours do not depend on the view), device {d.device}" +
             ("; Gaussian Grouping on mask-free clusters in the same training (spectral clustering of the "
              "Gaussians on the captured colour once densification stops; no Segment Anything weights here)"
              if joint else ""))
    if d.todo("reconstruct"):
        t0 = time.perf_counter()
        data = load_dataset(d.data_dir, num_random_points=sz.init_points, seed=d.seed, init="random",
                            progress=d.progress)
        it = sz.reconstruct_iters
        every = max(10, it // 25)
        # a short run: densify every 1/25 of it until half-way, no opacity reset, positions at 3x the 3DGS
        # rate (measured on this scene at 500 steps: +1.8 dB held out over the 3DGS rate)
        recipe = Recipe(sh_degree=0, lr_means=3 * Recipe.lr_means, lr_means_final=3 * Recipe.lr_means_final)
        strategy = DefaultStrategy(max_gaussians=sz.max_gaussians, refine_start=every, refine_every=every,
                                   refine_stop=it // 2, reset_every=0)
        resume_rec = (d.scene_dir / "checkpoint.pt").is_file()
        cfg = ReconstructConfig(iters=it, strategy=strategy, recipe=recipe, seed=d.seed,
                                checkpoint_every=max(50, it // 5), init="random")
        kw = dict(device=d.device, progress=d.progress, data=data, resume=resume_rec, force=not resume_rec)
        if joint:
            m = reconstruct_with_groups(d.data_dir, d.scene_dir, cfg, masks=None, max_groups=8, group_start=GROUP_START,
                                        config=GroupConfig(dim=sz.group_dim), **kw)
        else:
            m = reconstruct(d.data_dir, d.scene_dir, cfg, **kw)
        d.done("reconstruct", seconds=time.perf_counter() - t0, gaussians=m["num_gaussians"], psnr=m["psnr"],
               ssim=m["ssim"], iters=m["iters"], test_views=m["test_views"], groups=m.get("groups"))
    rec = d.stages["reconstruct"]
    d.times["reconstruct"] = rec["seconds"]
    d.say(f"      {rec['gaussians']} Gaussians, held-out PSNR {_fmt(rec['psnr'], '.2f')} dB "
          f"over {rec['test_views']} views")
    return rec


def _stage_group(d: _Demo, cams, objects, num_objects: int, resume: bool, sam) -> dict:
    """3: Gaussian Grouping on segmenter instances when SAM's weights are here (``sam``), else the mask-free groups
    trained with the reconstruction; both scored against the true objects."""
    d.header(3, "group", "Gaussian Grouping on Segment Anything instances associated across views" if sam else
             "the groups trained with the reconstruction, scored against the true objects")
    if d.todo("group"):
        t0 = time.perf_counter()
        joint = bool(d.stages["reconstruct"].get("groups"))
        if sam and not joint:
            made = make_masks(d.scene_dir, sam=sam, device=d.device, progress=d.progress, force=not resume,
                              resume=resume)
            if made["num_instances"] == 0:
                d.say("      Segment Anything found no instances: grouping on mask-free clusters instead")
                sam = None
        if joint:
            info = load_groups(d.scene_dir).info
        else:
            info = group_scene(d.scene_dir, masks="auto" if sam else None, max_groups=8,
                               config=GroupConfig(iters=d.sz.group_iters,
                               checkpoint_every=max(25, d.sz.group_iters // 4)), device=d.device, seed=d.seed,
                               progress=d.progress, resume=resume)
        scene = read_ply(d.scene_dir / "scene.ply", device=d.device)
        gm = load_groups(d.scene_dir, d.device)
        labels, _ = render_group_maps(scene, cams.to(d.device), gm.classifier)
        agree = group_agreement(labels, objects, num_objects)
        d.done("group", seconds=time.perf_counter() - t0, groups=info["num_groups"], kind=info["kind"], joint=joint,
               cross_view_agreement=info.get("reprojection_agreement", {}).get("mean"),
               purity=agree["purity"], separated=agree["separated"], objects=agree["objects"])
    grp = d.stages["group"]
    d.times["group"] = grp["seconds"]
    d.say(f"      K={grp['groups']} groups ({grp.get('kind')}); they match the {grp['objects']} true objects with "
          f"purity {_fmt(grp['purity'], '.3f')} ({grp['separated']} objects in a group of their own); "
          f"cross-view agreement {_fmt(grp['cross_view_agreement'], '.3f')}")
    return grp


def _stage_stylize(d: _Demo, resume: bool) -> dict:
    """4: key views, Stage 1 (when its weights are here), Stage 2."""
    sz = d.sz
    missing = _weights_missing()
    stage1_runs = not missing
    d.header(4, "stylize", "key views -> Stage 1 (diffusion + CVSA) -> Stage 2 (instance-level style transfer)")
    if not stage1_runs:
        d.say(f"      Stage 1 will be skipped: no local weights for {', '.join(missing)} "
              f"(`ssgwarp weights --download stage1` fetches them); Stage 2 then matches each group against its "
              f"own region of the style image")
    if d.todo("stylize"):
        t0 = time.perf_counter()
        opts = StylizeOptions(keyviews=sz.keyviews, max_side=512 if stage1_runs else sz.max_side,
                              path_frames=sz.path_frames, sheet_views=3)
        # direct back-propagation: the demo's views are small, so the deferred kind's saving of memory is not
        # needed, and it renders every view twice per step (the same gradient but for float rounding)
        s2 = Stage2Config(mode="ist", iters=sz.stylize_iters, lr=sz.stylize_lr, deferred=False,
                          checkpoint_every=max(10, sz.stylize_iters // 5), seed=d.seed)
        again = resume and d.styl_dir.exists()
        sm = stylize_run(d.scene_dir, d.out / "style.png", d.styl_dir, stage2=s2, opts=opts, device=d.device,
                         resume=again, force=not again, progress=d.progress)
        d.done("stylize", seconds=time.perf_counter() - t0, stage1=sm["stage1"], stage1_missing=missing,
               matching=sm["matching"], nnfm=_nnfm_history(d.styl_dir / "stage2.ckpt"),
               substages={k: round(v, 3) for k, v in sm["seconds"].items()},
               gram_style_loss=sm["gram_style_loss"], gram_style_loss_original=sm["gram_style_loss_original"],
               style_distance=sm["style_distance"], style_distance_original=sm["style_distance_original"],
               content_loss=sm["content_loss"], extractor=sm["extractor"], keyviews=sm["keyviews"],
               style_loss=sm["style_loss"], weight_free=not str(sm["extractor"]).startswith("vgg16"),
               color_transfer=sm["color_transfer"]["setting"])
    sty = d.stages["stylize"]
    d.times["stylize"] = sty["seconds"]
    d.say(f"      {_path(sty)}")
    d.say(f"      Stage 2 matched {sty['matching']}; {_distances(sty)}; Gram style loss "
          f"{_fmt(sty['gram_style_loss_original'])} -> {_fmt(sty['gram_style_loss'])}, content loss "
          f"{_fmt(sty['content_loss'])}")
    return sty


def _stage_evaluate(d: _Demo) -> tuple[dict, dict]:
    """5: both runs scored by ``ssgwarp evaluate``'s code; the table in ``OUT/evaluation.md``."""
    d.header(5, "evaluate", "consistency (reprojection), Gram style / content losses, PSNR")
    t0 = time.perf_counter()
    eopts = EvalOptions(max_pairs=d.sz.eval_pairs, gap=max(2, d.sz.views // 3), save_pairs=1).validate()
    extractor, raft, lpips, skipped = load_models(eopts, d.device)
    kw = dict(extractor=extractor, raft=raft, lpips=lpips, skipped=skipped, progress=d.progress)
    ev_rec = evaluate_run(d.scene_dir, eopts, d.device, **kw)
    ev_sty = evaluate_run(d.styl_dir, eopts, d.device, **kw)
    with atomic_path(d.out / "evaluation.md") as tmp:
        tmp.write_text(comparison_table([ev_rec, ev_sty]))
    d.times["evaluate"] = time.perf_counter() - t0
    d.done("evaluate", seconds=d.times["evaluate"])
    return ev_rec, ev_sty


def _stage_sheet(d: _Demo, cams, images, rec: dict, grp: dict, sty: dict) -> Path:
    """6: captured | reconstructed | groups | stylized rows of three views, and the style."""
    d.header(6, "sheet", "contact sheet")
    t0 = time.perf_counter()
    dev = d.device
    rec_scene = read_ply(d.scene_dir / "scene.ply", device=dev)
    sty_scene = read_ply(d.styl_dir / "scene.ply", device=dev)
    gm = load_groups(d.scene_dir, dev)
    test = set(Run.open(d.scene_dir).test_ids)
    rows_ids = sorted(test)[:3] if len(test) >= 3 else sorted({round(i * (d.sz.views - 1) / 3) for i in range(3)})
    bg = torch.tensor(P.BACKGROUND, dtype=torch.float32, device=dev)
    bg_sty = torch.tensor(Run.open(d.styl_dir).background(P.BACKGROUND), dtype=torch.float32, device=dev)
    rows = []
    with torch.no_grad():
        for i in rows_ids:
            cam = cams[[i]].to(dev)
            r, alpha, _ = rec_scene.render(cam, backgrounds=bg[None])
            s, _, _ = sty_scene.render(cam, backgrounds=bg_sty[None])   # its own, recoloured with it
            lab, _ = render_group_maps(rec_scene, cam, gm.classifier)
            groups = torch.from_numpy(colorize_labels(lab[0], gm.num_groups))
            empty = alpha[0, ..., 0].cpu() < 0.5           # no surface there: shown light grey, not as a group
            groups[empty] = 0.92
            rows.append({"label": f"{cams.names[i]}{' (held out)' if i in test else ''}", "captured": images[i],
                         "reconstruction": r[0, ..., :3], "stylized": s[0, ..., :3], "groups": groups})
    style = torch.from_numpy(read_image(d.out / "style.png", 3))
    title = (f"ssgwarp demo ({d.name}): {rec['gaussians']} Gaussians, PSNR {_fmt(rec['psnr'], '.2f')} dB, "
             f"K={grp['groups']} groups, Stage 1 {'ran' if sty['stage1'].get('ran') else 'skipped (no weights)'}, "
             f"{_distances(sty)}")
    sheet = _contact_sheet(d.out / "contact_sheet.png", rows, style, title, grp.get("kind", "mask-free clusters"))
    d.times["sheet"] = time.perf_counter() - t0
    d.done("sheet", seconds=d.times["sheet"])
    return sheet


def _rmse(ev: dict, kind: str):
    return ev.get("consistency", {}).get("reprojection", {}).get(kind, {}).get("rmse")


def _summary(d: _Demo, gt, rec: dict, grp: dict, sty: dict, evs: tuple[dict, dict], sheet: Path, total: float) -> dict:
    ev_rec, ev_sty = evs
    sz = d.sz
    return {
        "size": d.name, "views": sz.views, "resolution": [sz.width, sz.height], "device": str(d.device),
        "seed": d.seed, "seconds": {k: round(v, 2) for k, v in d.times.items()}, "total_seconds": round(total, 2),
        "stylize_substages": sty.get("substages"),
        "true_gaussians": len(gt), "objects": list(gt.names),
        "gaussians": rec["gaussians"], "psnr": rec["psnr"], "ssim": rec["ssim"],
        "groups": grp["groups"], "group_kind": grp.get("kind"), "group_purity": grp["purity"],
        "groups_trained_with": "reconstruct" if grp.get("joint") else "group",
        "objects_separated": grp["separated"],
        "cross_view_agreement": grp["cross_view_agreement"],
        "stage1": sty["stage1"], "stage1_missing_weights": sty.get("stage1_missing", []),
        "matching": sty["matching"], "extractor": sty["extractor"], "nnfm_style_loss": sty.get("nnfm"),
        "style_loss": sty.get("style_loss", "nnfm"), "weight_free": sty.get("weight_free", True),
        "color_transfer": sty.get("color_transfer", "off"),
        "gram_style_loss_original": sty["gram_style_loss_original"], "gram_style_loss": sty["gram_style_loss"],
        "style_distance_original": sty.get("style_distance_original"), "style_distance": sty.get("style_distance"),
        "content_loss": sty["content_loss"],
        "consistency_rmse": {"reconstruction": {"short": _rmse(ev_rec, "short"), "long": _rmse(ev_rec, "long")},
                             "stylized": {"short": _rmse(ev_sty, "short"), "long": _rmse(ev_sty, "long")}},
        "contact_sheet": str(sheet.resolve()),
        "outputs": {"data": str(d.data_dir), "style": str(d.out / "style.png"), "reconstruction": str(d.scene_dir),
                    "stylized": str(d.styl_dir), "evaluation": str(d.out / "evaluation.md")},
    }


def run_demo(out: str | Path = "ssgwarp-demo", size="default", *, device=None, seed: int = 0,
             force: bool = False, resume: bool = False, progress: bool = True,
             echo: Optional[Callable[[str], None]] = None) -> dict:
    """Run the demo into ``out`` and return the summary (also written to ``out/summary.json``).

    Args:
        out: output folder (created; never overwritten without ``force``).
        size: ``"small"`` (8 views 48x36, seconds), ``"default"`` (24 views 80x60, about half a
            minute on 2 idle CPU cores) or a :class:`ssgwarp.procedural.DemoSize`.
        device: torch device or ``"auto"``/None (the GPU when there is one).
        seed: seeds every stage; a seed gives the same run.
        force: overwrite an existing demo in ``out``. resume: continue one (after Ctrl-C).
        progress: progress bars and stage messages. echo: where messages go (default print).
    """
    say = echo or (lambda s: print(s, flush=True))
    if not progress and echo is None:
        say = lambda s: None  # noqa: E731
    t_all = time.perf_counter()
    name, sz = _size(size)
    out = Path(out).expanduser()
    record = {"format": FORMAT, "options": {"size": name, "seed": int(seed), **asdict(sz)}, "stages": {}}
    record = _prepare_out(out, force, resume, record)
    out.mkdir(parents=True, exist_ok=True)
    d = _Demo(out, name, sz, _resolve_device(device), seed, progress, say, record)
    write_json(out / "demo.json", record)
    # every weight lookup of every stage offline: what is on this machine is used, nothing is fetched
    with W.offline(OFFLINE_REASON):
        gt, cams, images, objects = _stage_data(d)
        sam = W.find("sam")
        rec = _stage_reconstruct(d, joint=not sam)
        grp = _stage_group(d, cams, objects, len(gt.names), resume, sam)
        sty = _stage_stylize(d, resume)
        evs = _stage_evaluate(d)
        sheet = _stage_sheet(d, cams, images, rec, grp, sty)
    summary = _summary(d, gt, rec, grp, sty, evs, sheet, time.perf_counter() - t_all)
    write_json(out / "summary.json", summary)
    return summary


def _path(d: dict) -> str:
    """Which Stage 2 path ran: with pretrained weights (Stage 1, VGG16) or weight-free."""
    st1 = "Stage 1 ran" if (d.get("stage1") or {}).get("ran") else "no Stage 1"
    if d.get("weight_free", True):
        what = f"weight-free ({st1}, random features {d.get('extractor')}"
    else:
        what = f"with pretrained weights ({st1}, VGG16 features"
    return (f"Stage 2 path: {what}, {str(d.get('style_loss', 'nnfm')).upper()} style loss, colour transfer "
            f"{d.get('color_transfer', 'off')})")


def _distances(d: dict) -> str:
    """'style distance colour a -> b, texture c -> d' (weight-free, lower = closer), or '' when absent."""
    b, a = d.get("style_distance_original") or {}, d.get("style_distance") or {}
    if not a:
        return "style distance n/a"
    return (f"style distance colour {_fmt(b.get('color'), '.3g')} -> {_fmt(a.get('color'), '.3g')}, "
            f"texture {_fmt(b.get('texture'), '.3g')} -> {_fmt(a.get('texture'), '.3g')}")


def _nnfm_history(ckpt: Path) -> Optional[list[float]]:
    """First and last Stage 2 style (NNFM) loss from the Stage 2 checkpoint's history, or None."""
    try:
        h = torch.load(ckpt, map_location="cpu", weights_only=False).get("history") or []
        vals = [float(x["style"]) for x in h if "style" in x]
        return [vals[0], vals[-1]] if vals else None
    except Exception:  # the history is a convenience: a missing or changed checkpoint just drops the line
        return None


def format_summary(s: dict) -> str:
    """The summary as the lines ``ssgwarp demo`` prints."""
    sec = s["seconds"]
    sub = s.get("stylize_substages") or {}
    st1 = s["stage1"]
    if st1.get("ran"):
        st1_line = f"ran (CVSA {'on' if st1.get('cvsa') else 'off'})"
    elif s.get("stage1_missing_weights"):
        st1_line = f"skipped: no local weights for {', '.join(s['stage1_missing_weights'])}"
    else:
        st1_line = f"skipped: {st1.get('reason', 'no weights')}"
    nn = s.get("nnfm_style_loss")
    nn_line = f", {str(s.get('style_loss', 'nnfm')).upper()} style loss {_fmt(nn[0])} -> {_fmt(nn[1])}" if nn else ""
    c = s["consistency_rmse"]
    lines = [
        f"ssgwarp demo ({s['size']}: {s['views']} views {s['resolution'][0]}x{s['resolution'][1]}, "
        f"device {s['device']}, seed {s['seed']}) finished in {s['total_seconds']:.1f} s",
        f"  {'stage':<22}{'time':>9}",
        f"  {'procedural data':<22}{sec.get('data', 0):>8.1f}s  {s['true_gaussians']} true Gaussians, "
        f"{len(s['objects'])} objects",
        f"  {'reconstruct':<22}{sec.get('reconstruct', 0):>8.1f}s  {s['gaussians']} Gaussians, held-out PSNR "
        f"{_fmt(s['psnr'], '.2f')} dB, SSIM {_fmt(s['ssim'], '.3f')}",
        f"  {'group':<22}{sec.get('group', 0):>8.1f}s  K={s['groups']} {s.get('group_kind')}"
        f"{' (trained in the reconstruction)' if s.get('groups_trained_with') == 'reconstruct' else ''}, purity vs true objects "
        f"{_fmt(s['group_purity'], '.3f')}, {s['objects_separated']}/{len(s['objects'])} objects separated, "
        f"cross-view agreement {_fmt(s['cross_view_agreement'], '.3f')}",
        f"  {'  key views':<22}{sub.get('keyviews', 0):>8.1f}s",
        f"  {'  Stage 1 (diffusion)':<22}{sub.get('stage1', 0):>8.1f}s  {st1_line}",
        f"  {'  Stage 2 (IST)':<22}{sub.get('stage2', 0):>8.1f}s  matching {s['matching']}{nn_line}",
        f"  {_path(s)}",
        f"  {'  renders + metrics':<22}{sub.get('renders', 0) + sub.get('metrics', 0):>8.1f}s",
        f"  {'evaluate':<22}{sec.get('evaluate', 0):>8.1f}s",
        f"  {'contact sheet':<22}{sec.get('sheet', 0):>8.1f}s",
        f"  {_distances(s)}; Gram style loss {_fmt(s['gram_style_loss_original'])} -> "
        f"{_fmt(s['gram_style_loss'])} (features {s['extractor']}), content loss {_fmt(s['content_loss'])}",
        f"  consistency RMSE (reprojection, short/long range): reconstruction "
        f"{_fmt(c['reconstruction']['short'], '.4f')}/{_fmt(c['reconstruction']['long'], '.4f')}, stylized "
        f"{_fmt(c['stylized']['short'], '.4f')}/{_fmt(c['stylized']['long'], '.4f')}",
        f"  evaluation table: {s['outputs']['evaluation']}",
        f"contact sheet: {s['contact_sheet']}",
    ]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the README's claims
# How far a fresh run may be from the numbers docs/make_figures.py wrote into the README and docs/demo.md (the
# reconstruction's last bits depend on the machine's thread count; tests/test_demo.py holds a run to them).
CLAIM_TOLERANCE = {"purity": 0.02, "distance": 0.05}
_NUM = r"(\d+(?:\.\d+)?)"
_CLAIM_RE = (rf"K = (?P<groups>\d+) groups, (?P<separated>\d+) of (?P<objects>\d+) objects in a group of their own, "
             rf"purity (?P<purity>{_NUM[1:-1]}) against the true objects; weight-free style distance colour "
             rf"(?P<color0>{_NUM[1:-1]}) -> (?P<color1>{_NUM[1:-1]}), texture (?P<texture0>{_NUM[1:-1]}) -> "
             rf"(?P<texture1>{_NUM[1:-1]})")


def claims(summary: dict) -> dict:
    """The demo numbers the README states, from a summary: groups, objects separated, purity, style distances."""
    b, a = summary.get("style_distance_original") or {}, summary.get("style_distance") or {}
    return {"groups": int(summary["groups"]), "separated": int(summary["objects_separated"]),
            "objects": len(summary["objects"]), "purity": float(summary["group_purity"]),
            "color0": b.get("color"), "color1": a.get("color"), "texture0": b.get("texture"),
            "texture1": a.get("texture")}


def claims_text(summary: dict) -> str:
    """The sentence docs/make_figures.py writes between the ``<!-- figures:demo -->`` markers."""
    c = claims(summary)
    return (f"K = {c['groups']} groups, {c['separated']} of {c['objects']} objects in a group of their own, purity "
            f"{c['purity']:.2f} against the true objects; weight-free style distance colour {c['color0']:.1f} -> "
            f"{c['color1']:.1f}, texture {c['texture0']:.2f} -> {c['texture1']:.2f}")


def parse_claims(text: str) -> dict:
    """The numbers of a :func:`claims_text` sentence inside ``text`` (ValueError when there is none)."""
    import re

    m = re.search(_CLAIM_RE, " ".join(text.split()))
    if m is None:
        raise ValueError("no demo claims sentence found")
    return {k: (int(v) if k in ("groups", "separated", "objects") else float(v)) for k, v in m.groupdict().items()}


def claims_hold(stated: dict, measured: dict) -> list[str]:
    """What of ``measured`` (:func:`claims`) differs from ``stated`` (:func:`parse_claims`) beyond
    :data:`CLAIM_TOLERANCE`: one line per difference, empty when the claims hold."""
    bad = [f"{k}: stated {stated[k]}, measured {measured[k]}" for k in ("groups", "separated", "objects")
           if stated[k] != measured[k]]
    if abs(stated["purity"] - measured["purity"]) > CLAIM_TOLERANCE["purity"]:
        bad.append(f"purity: stated {stated['purity']}, measured {measured['purity']:.3f}")
    for k in ("color0", "color1", "texture0", "texture1"):
        if measured[k] is None or abs(measured[k] - stated[k]) > CLAIM_TOLERANCE["distance"] * abs(stated[k]):
            bad.append(f"style distance {k}: stated {stated[k]}, measured {measured[k]}")
    return bad


__all__ = ["run_demo", "format_summary", "group_agreement", "claims", "claims_text", "parse_claims", "claims_hold", "OUTPUTS", "STAGES"]
