"""``ssgwarp evaluate``: consistency and style / content / quality metrics of runs, side by side.

A run folder is either

* a reconstruction (``scene.ply``, ``cameras.json``, ``data.json``), or
* a stylize output (``scene.ply`` + ``metrics.json`` naming its ``source_scene``
  reconstruction and its ``style`` image).

For each run: render the scored cameras — by default novel views on a smooth
camera path through the training cameras (``--views path``; ``test`` = the
held-out captured views, ``train`` / ``all`` the old behaviour) —, measure
short-range (adjacent views) and long-range (views ``--gap`` apart)
consistency by warping view A into view B (:mod:`ssgwarp.evaluation.metrics`), the Gram
style loss and the weight-free style distances (colour and filter-bank sliced
Wasserstein, :class:`ssgwarp.evaluation.metrics.StyleDistance`) against the style image,
the content loss against the unstylized source renders (stylize outputs), and
PSNR / SSIM against the captured test images (reconstructions). Results go into ``RUN/metrics.json`` under ``"evaluation"``
(other keys are kept), inspection images into ``RUN/evaluation/``, and one
markdown table compares all runs (``--table``, printed too).
"""
from __future__ import annotations

import datetime as _dt
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import torch
from ..core.progress import tqdm

from . import metrics as M
from . import networks as N
from ..core.cameras import Cameras
from ..capture.loaders import resize_images
from ..errors import InputError, SsgwarpError, WeightsNotFound
from .table import PAIR_KINDS
from .features import load_extractor
from ..core.fileio import read_image, write_image
from .metrics import extractor_from_name, reconstruction_quality, style_scores
from .render import smooth_path
from ..raster.rendering import render_views
from ..services.runs import Run, update_metrics

RunInfo = Run                # (the run folder: ssgwarp.services.runs.Run)
inspect_run = Run.open

WARPS = ("auto", "reprojection", "flow", "both")
VIEW_SETS = ("path", "test", "train", "all")


# ----------------------------------------------------------------------------- options
@dataclass
class EvalOptions:
    """Options of :func:`evaluate_run` (CLI flags of the same names)."""

    style: Optional[str] = None          # style image (default: the one the stylize run recorded)
    pairs: tuple[str, ...] = PAIR_KINDS
    gap: int = 7                         # long-range view gap
    max_pairs: int = 16                  # per kind (0: all)
    views: str = "path"                  # path (novel views) | test (held out) | train | all
    path_frames: int = 30                # frames of the novel-view path (views=path)
    max_side: int = 0                    # evaluate at this longer image side (0: the cameras' resolution)
    depth_tol: float = 0.02              # relative depth tolerance of the occlusion test
    alpha_min: float = 0.9               # pixels with lower render alpha are not compared
    warp: str = "auto"                   # auto: reprojection, plus flow when RAFT weights are found
    flow_iters: int = 12
    save_pairs: int = 3                  # inspection strips saved per kind and warp
    vgg: Optional[str] = None
    lpips: Optional[str] = None
    raft: Optional[str] = None
    layers: Optional[list[str]] = None   # VGG16 layers of the style/content features
    data_dir: Optional[str] = None
    weights_config: Optional[dict] = None

    def validate(self) -> "EvalOptions":
        bad = [p for p in self.pairs if p not in PAIR_KINDS]
        if bad or not self.pairs:
            raise InputError(f"--pairs {','.join(self.pairs)}: use short, long or short,long")
        if self.gap < 1:
            raise InputError(f"--gap {self.gap}: must be >= 1")
        if self.max_pairs < 0:
            raise InputError(f"--max-pairs {self.max_pairs}: must be >= 0 (0 = all pairs)")
        if self.views not in VIEW_SETS:
            raise InputError(f"--views {self.views}: use {', '.join(VIEW_SETS)}")
        if self.path_frames < 2:
            raise InputError(f"--path-frames {self.path_frames}: must be >= 2 (consistency needs pairs)")
        if self.max_side < 0:
            raise InputError(f"--max-side {self.max_side}: must be >= 0")
        if not 0 < self.depth_tol < 1:
            raise InputError(f"--depth-tol {self.depth_tol}: must be in (0, 1)")
        if not 0 <= self.alpha_min <= 1:
            raise InputError(f"--alpha-min {self.alpha_min}: must be in [0, 1]")
        if self.warp not in WARPS:
            raise InputError(f"--warp {self.warp}: use one of {', '.join(WARPS)}")
        if self.flow_iters < 1:
            raise InputError(f"--flow-iters {self.flow_iters}: must be >= 1")
        if self.style is not None and not Path(self.style).is_file():
            raise InputError(f"--style {self.style}: image not found")
        return self


def _scaled(cams: Cameras, max_side: int) -> Cameras:
    if max_side <= 0 or max(cams.width, cams.height) <= max_side:
        return cams
    k = max_side / max(cams.width, cams.height)
    return cams.rescaled(max(1, round(cams.width * k)), max(1, round(cams.height * k)))


def _select(n: int, train: Sequence[int], test: Sequence[int], which: str) -> list[int]:
    if which == "train":
        ids = list(train)
    elif which == "test":
        ids = list(test)
    else:
        ids = list(range(n))
    return sorted(ids)


def scored_cameras(cameras: Cameras, train: Sequence[int], test: Sequence[int], opts: EvalOptions
                   ) -> tuple[Cameras, Optional[list[int]], str]:
    """The cameras ``evaluate`` scores, their capture indices (None for path views) and a description.

    ``path``: ``opts.path_frames`` novel views on :func:`ssgwarp.evaluation.render.smooth_path` through the
    training cameras (as the 3D style transfer papers score videos along a path), taken half a
    frame off the path's start so that no frame sits on the training camera the path starts at;
    ``test``: the held-out captured views; ``train`` / ``all``: captured views.
    """
    if opts.views == "path":
        base = list(train) or list(range(len(cameras)))
        # the odd frames of a path twice as dense: the path starts on a training camera, these do not
        cams = smooth_path(cameras[base], 2 * opts.path_frames)[list(range(1, 2 * opts.path_frames, 2))]
        cams.names = [f"frame_{i:04d}" for i in range(len(cams))]
        return cams, None, (f"{opts.path_frames} novel views on a smooth path through the {len(base)} "
                            f"training cameras")
    ids = _select(len(cameras), train, test, opts.views)
    what = {"test": "held-out (test) captured views", "train": "training views",
            "all": "all captured views (training and held out)"}[opts.views]
    return cameras[ids], ids, f"{len(ids)} {what}"


# ----------------------------------------------------------------------------- pieces
def _finite(x: float) -> Optional[float]:
    return None if x is None or not math.isfinite(x) else float(x)


def _save_strip(path: Path, a: torch.Tensor, warped: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> None:
    """PNG strip: A | A warped into B | B | mask | 4x |warped - B| on the mask."""
    m = mask.to(b.dtype)[..., None]
    err = ((warped - b).abs() * 4.0 * m).clamp(0, 1)
    if a.shape != b.shape:
        a = torch.nn.functional.interpolate(a.permute(2, 0, 1)[None], size=b.shape[:2], mode="bilinear",
                                            align_corners=False)[0].permute(1, 2, 0)
    sep = torch.ones(b.shape[0], 2, 3, dtype=b.dtype, device=b.device)
    strip = torch.cat([a, sep, warped, sep, b, sep, m.expand_as(b), sep, err], dim=1)
    write_image(path, strip.float().cpu())
    write_image(path.with_name(path.stem + "_mask.png"), m.float().cpu())


@torch.no_grad()
def consistency(images: torch.Tensor, depths: torch.Tensor, alphas: torch.Tensor, cams: Cameras,
                opts: EvalOptions, *, raft=None, lpips=None, save_dir: Optional[Path] = None,
                names: Optional[Sequence[str]] = None, desc: Optional[str] = None) -> dict:
    """Short-/long-range consistency of rendered views ``images [V,H,W,3]``, ``depths/alphas [V,H,W]``.

    Returns ``{warp: {kind: {"gap", "pairs", "rmse", "rmse_std", "lpips", "coverage"}}}``.
    """


    warps = []
    if opts.warp in ("auto", "reprojection", "both"):
        warps.append("reprojection")
    if opts.warp in ("flow", "both") or (opts.warp == "auto" and raft is not None):
        warps.append("flow")
    V = images.shape[0]
    names = list(names) if names is not None else [f"{i:04d}" for i in range(V)]
    jobs = []
    for kind in opts.pairs:
        pairs = M.consistency_pairs(V, kind, opts.gap, opts.max_pairs or None)
        jobs += [(kind, a, b) for a, b in pairs]
    per: dict[str, dict[str, dict[str, list]]] = {w: {k: {"rmse": [], "lpips": [], "coverage": []}
                                                       for k in opts.pairs} for w in warps}
    saved: dict[tuple[str, str], int] = {}
    flow_cache: dict[tuple[int, int], torch.Tensor] = {}

    def flow(a: int, b: int) -> torch.Tensor:
        if (a, b) not in flow_cache:
            flow_cache[(a, b)] = N.estimate_flow(raft, images[a], images[b], iters=opts.flow_iters)
        return flow_cache[(a, b)]

    views = [M.View(images[i], depths[i], alphas[i], cams.viewmats[i], cams.Ks[i]) for i in range(V)]
    for kind, a, b in tqdm(jobs, desc=desc, disable=desc is None, leave=False):
        for w in warps:
            if w == "reprojection":
                res = M.reprojection_warp(views[a], views[b], rel_tol=opts.depth_tol, alpha_min=opts.alpha_min)
            else:
                res = M.flow_warp(images[a], images[b], flow(a, b), flow_ba=flow(b, a), alpha_a=alphas[a],
                                  alpha_b=alphas[b], alpha_min=opts.alpha_min)
            d = per[w][kind]
            d["rmse"].append(M.masked_rmse(res.warped, images[b], res.mask))
            d["coverage"].append(float(res.mask.float().mean()))
            if lpips is not None and bool(res.mask.any()):
                m = res.mask.to(images.dtype)[..., None]
                x = (res.warped * m).permute(2, 0, 1)[None]
                y = (images[b] * m).permute(2, 0, 1)[None]
                d["lpips"].append(float(lpips(x, y)[0]))
            if save_dir is not None and saved.get((w, kind), 0) < opts.save_pairs:
                saved[(w, kind)] = saved.get((w, kind), 0) + 1
                _save_strip(save_dir / f"{kind}_{w}_{names[a]}-{names[b]}.png", images[a], res.warped,
                            images[b], res.mask)
    out: dict[str, dict] = {}
    for w in warps:
        out[w] = {}
        for kind in opts.pairs:
            d = per[w][kind]
            rm = [x for x in d["rmse"] if math.isfinite(x)]
            t = torch.tensor(rm, dtype=torch.float64)
            out[w][kind] = {
                "gap": 1 if kind == "short" else max(1, min(opts.gap, V - 1)),
                "pairs": len(d["rmse"]),
                "pairs_with_overlap": len(rm),
                "rmse": _finite(float(t.mean())) if rm else None,
                "rmse_std": _finite(float(t.std(unbiased=False))) if rm else None,
                "lpips": _finite(sum(d["lpips"]) / len(d["lpips"])) if d["lpips"] else None,
                "coverage": _finite(sum(d["coverage"]) / len(d["coverage"])) if d["coverage"] else None,
            }
    return out


def _load_style(path: Path, device) -> torch.Tensor:
    return torch.from_numpy(read_image(path, channels=3)).to(device)


# ----------------------------------------------------------------------------- one run
def _desc(what: str, info, progress: bool) -> Optional[str]:
    """The progress bar's label (``render RUN``), or None (no bar) without ``progress``."""
    return f"{what} {info.path.name}" if progress else None


def evaluate_run(run_dir: str | Path, opts: EvalOptions, device: torch.device | str = "cpu", *,
                 extractor=None, raft=None, lpips=None, skipped: Optional[dict] = None,
                 write: bool = True, progress: bool = True) -> dict:
    """Evaluate one run folder; returns the ``evaluation`` dict (also merged into ``RUN/metrics.json``).
    ``progress``: progress bars of the renders and the pairs."""
    opts.validate()
    device = torch.device(device)
    info = inspect_run(run_dir)
    t0 = time.time()
    out_dir = info.path / "evaluation"
    skipped = dict(skipped or {})
    result: dict[str, Any] = {
        "run": str(info.path), "kind": info.kind, "date": _dt.datetime.now().isoformat(timespec="seconds"),
        "device": _device_name(device),
    }
    if info.mode:
        result["mode"] = info.mode

    # cameras, split, background, the scene (and the source scene of a stylized run)
    need_images = info.kind == "reconstruction"
    try:
        scene, data = info.load(device, data_dir=opts.data_dir, load_images=need_images, progress=progress)
    except InputError as e:
        if not need_images:
            raise
        skipped["quality"] = f"captured images not available ({e})"
        scene, data = info.load(device, data_dir=opts.data_dir, load_images=False)
        need_images = False
    src_scene = Run.reconstruction(info.source_dir).scene(device) if info.kind == "stylized" else scene
    if opts.views != "path" and not _select(len(data.cameras), data.train_ids, data.test_ids, opts.views):
        raise InputError(f"{info.path}: no '{opts.views}' views to evaluate (try --views path or all)")
    cams, ids, scored = scored_cameras(data.cameras, data.train_ids, data.test_ids, opts)
    cams = _scaled(cams, opts.max_side).to(device)
    names = [Path(n).stem for n in cams.names]
    bg = list(data.background)                       # the capture's: the unstylized source is shown on it
    bg_run = info.background(bg)                      # a stylized run's own (recoloured with the scene)
    result.update({"views": len(cams), "view_split": opts.views, "views_scored": scored,
                   "resolution": [cams.width, cams.height],
                   "gaussians": len(scene), "sh_degree": scene.sh_degree, "background": bg_run})

    rgb, depth, alpha = render_views(scene, cams, bg_run, desc=_desc("render", info, progress))
    result["consistency"] = consistency(rgb, depth, alpha, cams, opts, raft=raft, lpips=lpips,
                                        save_dir=out_dir / "pairs", names=names,
                                        desc=_desc("pairs", info, progress))
    result["consistency_settings"] = {"depth_tol": opts.depth_tol, "alpha_min": opts.alpha_min,
                                      "max_pairs": opts.max_pairs, "gap": opts.gap,
                                      "flow_iters": opts.flow_iters if raft is not None else None}

    # style / content
    style_path = Path(opts.style) if opts.style else info.style
    sc: dict[str, Any] = {}
    style = None
    if style_path is not None and style_path.is_file():
        style = _load_style(style_path, device)
        sc["style_image"] = str(style_path)
    elif style_path is not None:
        skipped["style"] = f"style image {style_path} not found (pass --style)"
    else:
        skipped.setdefault("style", "no style image (pass --style)")
    originals = orig_alpha = None
    if info.kind == "stylized" and (extractor is not None or style is not None):
        originals, _, orig_alpha = render_views(src_scene, cams, bg, desc=_desc("source", info, progress))
    if extractor is not None:
        extractor, note = _run_extractor(info, extractor, device, opts)
        sc["extractor"] = getattr(extractor, "name", type(extractor).__name__)
        if note:
            sc["extractor_note"] = note
    if extractor is not None or style is not None:
        # the one definition stylize reports too (on its training views: --views train reproduces them)
        numbers = style_scores(extractor, rgb, style, originals, alphas=alpha, original_alphas=orig_alpha)
        if numbers:
            sc.update(numbers, views=scored)
    if sc:
        result["style_content"] = sc

    # reconstruction quality
    if info.kind == "reconstruction" and need_images:
        qids = data.test_ids or data.train_ids
        qsplit = "test" if data.test_ids else "train"
        qcams = _scaled(data.cameras[qids], opts.max_side).to(device)
        targets = data.images[qids].to(device)
        if targets.shape[1:3] != (qcams.height, qcams.width):
            targets = resize_images(targets, qcams.height, qcams.width)
        pos = {i: k for k, i in enumerate(ids or [])}
        if ids is not None and all(i in pos for i in qids) and qcams.width == cams.width:
            renders = rgb[[pos[i] for i in qids]]
        else:
            renders, _, _ = render_views(scene, qcams, bg, desc=_desc("quality", info, progress))
        q = reconstruction_quality(renders, targets)
        qd: dict[str, Any] = {"split": qsplit, "views": len(qids),
                              "psnr": sum(q["psnr"]) / len(q["psnr"]), "ssim": sum(q["ssim"]) / len(q["ssim"]),
                              "metric_frame": data.metric_frame["metric_frame"]}
        if lpips is not None:
            with torch.no_grad():
                vals = [float(lpips(r.permute(2, 0, 1)[None], t.permute(2, 0, 1)[None])[0])
                        for r, t in zip(renders, targets)]
            qd["lpips"] = sum(vals) / len(vals)
        result["quality"] = qd
    if skipped:
        result["skipped"] = skipped
    result["time_s"] = round(time.time() - t0, 3)

    if write:
        update_metrics(info.path, {"evaluation": _clean(result)})
    return _clean(result)


def _run_extractor(info: Run, extractor, device, opts: EvalOptions) -> tuple[Any, Optional[str]]:
    """The extractor a stylize run recorded (its numbers are then reproducible), else ``extractor``;
    with a note when they differ."""
    recorded = info.recorded.get("extractor") if info.kind == "stylized" else None
    have = getattr(extractor, "name", None)
    if not recorded or recorded == have:
        return extractor, None
    try:
        return extractor_from_name(recorded, device, vgg_weights=opts.vgg, config=opts.weights_config), None
    except (InputError, WeightsNotFound) as e:
        return extractor, f"stylize used {recorded} ({_one_line(e)[:120]}); Gram / content numbers differ from its"


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def _clean(obj: Any) -> Any:
    """JSON-safe copy: NaN / inf become None, tensors become numbers."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, torch.Tensor):
        return _clean(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _device_name(device: torch.device) -> str:
    if device.type == "cuda" and torch.cuda.is_available():
        return f"cuda ({torch.cuda.get_device_name(device)})"
    import platform

    return f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def load_models(opts: EvalOptions, device) -> tuple[Any, Any, Any, dict]:
    """``(extractor, raft or None, lpips or None, skipped reasons)`` for ``opts``.

    Weights come through :mod:`ssgwarp.services.weights`: found, or downloaded on first use unless downloads are off.
    """

    skipped: dict[str, str] = {}
    raft = None
    if opts.warp in ("flow", "both"):     # required: raises WeightsNotFound, before any other model is reported
        raft = N.load_raft(opts.raft, device, opts.weights_config)
    extractor = load_extractor(opts.vgg, device, layers=opts.layers, config=opts.weights_config)
    if opts.warp == "auto":
        try:
            raft = N.load_raft(opts.raft, device, opts.weights_config)
        except WeightsNotFound as e:
            if opts.raft:
                raise
            skipped["flow warp"] = str(e)
    lpips = None
    try:
        lpips = N.load_lpips(opts.lpips, opts.vgg, device, opts.weights_config)
    except WeightsNotFound as e:
        if opts.lpips:
            raise
        skipped["lpips"] = str(e)
    return extractor, raft, lpips, skipped


def claim_evaluation(info: Run, force: bool):
    """Refuse a run evaluated before (``RUN/evaluation/`` or the ``evaluation`` entry of ``RUN/metrics.json``)
    unless ``force``: the overwrite policy of every stage (:func:`ssgwarp.services.runs.claim`)."""
    from ..services.runs import claim

    if not force and isinstance(info.recorded, dict) and "evaluation" in info.recorded:
        raise SsgwarpError(f"{info.path} already holds an evaluation (the 'evaluation' entry of metrics.json); "
                           f"pass --force to overwrite it")
    return claim(info.path, ["evaluation"], force=force, what="an evaluation", resumable=False)


def style_line(sc: dict) -> str:
    """The style / content numbers of one run as one line, with the views and extractor they were computed on."""
    g = lambda k: f"{sc[k]:.4g}" if sc.get(k) is not None else "n/a"  # noqa: E731
    parts = [f"Gram style loss {g('gram_style_loss')}" if "gram_style_loss" in sc else "",
             f"content {g('content_loss')}" if "content_loss" in sc else "",
             f"style distance colour {g('style_distance_color')}, texture {g('style_distance_texture')}"
             if "style_distance_color" in sc else "",
             f"empty regions {g('empty_spread')} (unstylized {g('empty_spread_original')})"
             if "empty_spread" in sc else ""]
    ext = f", {sc['extractor']}" if sc.get("extractor") else ""
    return f"on {sc.get('views', 'the scored views')}{ext}: " + "; ".join(p for p in parts if p)


__all__ = ["EvalOptions", "RunInfo", "inspect_run", "consistency", "evaluate_run", "scored_cameras",
           "load_models", "claim_evaluation", "style_line"]
