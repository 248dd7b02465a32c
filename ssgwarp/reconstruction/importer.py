"""Splats trained by other tools as an ssgwarp run: ``ssgwarp import SOURCE --out RUN``.

``SOURCE`` is one of (detected, or named with ``--tool``):

* ``graphdeco``: a graphdeco 3DGS output folder (``point_cloud/iteration_N/point_cloud.ply``, the
  highest N or ``--iteration``; ``cameras.json``; ``cfg_args``). The capture is the one ``cfg_args``
  names (``source_path``, ``images``, ``resolution``, ``white_background``, ``eval``), or ``--data``;
  when it cannot be found the run holds ``cameras.json``'s cameras and no images (no PSNR);
* ``gsplat``: a gsplat ``simple_trainer`` result folder (``ckpts/ckpt_STEP_rank0.pt``, the highest
  STEP or ``--iteration``; else ``ply/point_cloud_STEP.ply``) or one such file, with ``--data`` the
  COLMAP capture it was trained on (or ``data_dir`` of the folder's ``cfg.yml``);
* ``nerfstudio``: the PLY of ``ns-export gaussian-splat`` with ``--data`` the dataset folder
  (``transforms.json``, or the COLMAP folder of nerfstudio's colmap dataparser) and the run's
  ``dataparser_transforms.json`` (``--dataparser-transforms``, or found beside the PLY);
* ``ply``: any splat file (INRIA-layout PLY, compressed PLY, SPZ, ``.splat``:
  :func:`ssgwarp.formats.registry.read_splat_file`) with ``--data`` any capture ssgwarp loads (COLMAP, LLFF, transforms);
  without ``--data``, a run with cameras made around its splats (:mod:`ssgwarp.capture.orbit`; no PSNR).

The splats are moved into the capture's frame (:mod:`ssgwarp.formats.layouts`): each layout gives
the candidate frames it may be in (graphdeco: the capture's own, or the similarity that aligns its
cameras.json to the capture's cameras; gsplat: its normalised world, or the capture's; nerfstudio:
the dataparser transform; a bare PLY: the capture's own frame, or gsplat's normalised one for a COLMAP
capture). Each candidate renders a few training views; the best is kept when it explains the images
better than their flat mean colour does and the splats project into the images; otherwise the import
stops with one line saying the frames do not match.

The run folder is a reconstruction run (``scene.ply``, ``cameras.json``, ``data.json``,
``metrics.json``; :mod:`ssgwarp.reconstruction.reconstruct`'s files), so ``group``, ``keyviews``,
``stylize``, ``render``, ``view`` and ``evaluate`` take it unchanged. ``metrics.json`` holds the
held-out and training PSNR / SSIM of the imported splats against the capture's images and an
``imported`` record (tool, files, the frame chosen and every candidate's score).
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from ..core.progress import tqdm

from ..formats.colmap import find_model, read_model
from ..capture.datasets import SceneData, load_dataset
from ..capture.loaders import IMAGE_EXTS
from ..capture.orbit import parse_up
from ..formats.ply import read_ply
from ..formats.registry import is_splat_file, read_splat_file
from ..formats.layouts import (graphdeco_cameras, graphdeco_folder, gsplat_checkpoints, gsplat_normalization,
                               match_names, nerfstudio_to_capture, read_gsplat_checkpoint, transform_scene)
from ..core.cameras import Cameras
from ..core.fileio import read_json, write_json
from ..core.frames import Similarity, umeyama
from ..core.geometry import project
from ..errors import InputError
from ..evaluation.metrics import reconstruction_quality
from ..raster.rendering import render_views
from ..raster.scene import GaussianScene
from ..services.runs import RUN_FILES, claim, write_orbit_run, write_run

log = logging.getLogger("ssgwarp.reconstruction.importer")

OUTPUTS = RUN_FILES
TOOLS = ("graphdeco", "gsplat", "nerfstudio", "ply")
PROBE_VIEWS = 6          # training views each candidate frame renders
MIN_GAIN_DB = 1.0        # how much better than the images' flat mean colour the splats must render
MIN_COVERAGE = 0.25      # fraction of the splats whose centres must fall inside some image

__all__ = ["OUTPUTS", "TOOLS", "detect_tool", "import_splats"]


# ----------------------------------------------------------------------------- detection
def detect_tool(source: Path, dataparser_transforms: Optional[Path] = None) -> str:
    if not source.exists():
        raise InputError(f"{source}: not found")
    if source.is_dir():
        if list((source / "point_cloud").glob("iteration_*/point_cloud.ply")):
            return "graphdeco"
        if gsplat_checkpoints(source) or list((source / "ply").glob("point_cloud_*.ply")):
            return "gsplat"
        raise InputError(f"{source}: neither a graphdeco 3DGS output (point_cloud/iteration_N/point_cloud.ply) "
                         f"nor a gsplat result folder (ckpts/ckpt_*.pt or ply/point_cloud_*.ply); pass a PLY "
                         f"file with --data for other tools")
    if source.suffix == ".pt":
        return "gsplat"
    if source.suffix.lower() == ".ply" and (dataparser_transforms is not None or
                                            (source.parent / "dataparser_transforms.json").is_file()):
        return "nerfstudio"
    if is_splat_file(source):
        return "ply"
    raise InputError(f"{source}: expected a folder, a splat file (PLY, compressed PLY, SPZ, .splat) or a gsplat .pt "
                     f"checkpoint")


def _cfg_yml(folder: Path) -> dict:
    """``data_dir``, ``data_factor``, ``test_every``, ``normalize_world_space`` of a gsplat ``cfg.yml``
    (read line by line: the file also holds Python object tags a safe YAML reader refuses)."""
    out: dict = {}
    p = folder / "cfg.yml"
    if not p.is_file():
        return out
    for line in p.read_text(errors="replace").splitlines():
        m = re.fullmatch(r"(data_dir|data_factor|test_every|normalize_world_space):\s*(.*?)\s*", line)
        if m:
            v = m.group(2).strip("'\"")
            out[m.group(1)] = int(v) if v.isdigit() else (v.lower() == "true" if v.lower() in ("true", "false") else v)
    return out


# ----------------------------------------------------------------------------- frames
def _coverage(scene: GaussianScene, cams: Cameras, max_cams: int = 64) -> float:
    """Fraction of the splats whose centres project in front of and inside at least one camera."""
    ids = np.unique(np.linspace(0, len(cams) - 1, min(len(cams), max_cams)).round().astype(int))
    x = scene.means.detach().double().cpu()
    seen = torch.zeros(len(x), dtype=torch.bool)
    for i in ids.tolist():
        uv, z = project(x, cams.viewmats[i].double(), cams.Ks[i].double())
        seen |= (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cams.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cams.height)
    return float(seen.double().mean())


def _flat_psnr(images: torch.Tensor) -> float:
    flat = images.mean(dim=(1, 2), keepdim=True).expand_as(images)
    return float(np.mean(reconstruction_quality(flat, images)["psnr"]))


def _choose_frame(scene: GaussianScene, candidates: list[tuple[str, Similarity]], data: Optional[SceneData],
                  cams: Cameras, background, device, source: Path,
                  progress: bool = False) -> tuple[str, Similarity, GaussianScene, list]:
    """The candidate frame whose renders best match the images (see the module docs)."""
    probe = []
    if data is not None:
        tr = data.train_ids or list(range(len(data)))
        probe = [tr[i] for i in np.unique(np.linspace(0, len(tr) - 1, min(len(tr), PROBE_VIEWS)).round().astype(int))]
    scored = []
    for label, sim in tqdm(candidates, desc="trying frames", unit="frame", disable=not progress or len(candidates) < 2,
                           leave=False):
        moved = transform_scene(scene, sim)
        cov = _coverage(moved, cams)
        psnr = None
        if probe:
            v = render_views(moved.to(device), cams[probe], background, depth=False)
            psnr = float(np.mean(reconstruction_quality(v.rgb.cpu(), data.images[probe].cpu())["psnr"]))
        scored.append({"frame": label, "coverage": round(cov, 4), "probe_psnr": None if psnr is None else round(psnr, 3),
                       "sim": sim})
        del moved
    best = max(scored, key=lambda s: (s["probe_psnr"] if s["probe_psnr"] is not None else 0.0, s["coverage"]))
    flat = _flat_psnr(data.images[probe].cpu()) if probe else None
    record = [{k: v for k, v in s.items() if k != "sim"} for s in scored]
    ok = best["coverage"] >= MIN_COVERAGE and (flat is None or best["probe_psnr"] >= flat + MIN_GAIN_DB)
    if not ok:
        where = data.data_dir if data is not None else "the cameras"
        why = []
        if best["coverage"] < MIN_COVERAGE:
            why.append(f"only {best['coverage']:.0%} of the splats fall inside any image")
        if flat is not None and best["probe_psnr"] < flat + MIN_GAIN_DB:
            why.append(f"its renders reach {best['probe_psnr']:.1f} dB against the images, where their flat mean "
                       f"colour gives {flat:.1f} dB")
        raise InputError(f"{source}: the splats do not match the frame of {where} (best frame tried, "
                         f"{best['frame']}: {'; '.join(why)}; tried {len(scored)} frame(s)); pass the capture they "
                         f"were trained on (--data) and the tool's own files (--tool, --dataparser-transforms)")
    for r in record:
        r["flat_psnr"] = None if flat is None else round(flat, 3)
    return best["frame"], best["sim"], transform_scene(scene, best["sim"]), record


# ----------------------------------------------------------------------------- the capture
def _image_width(folder: Path) -> Optional[int]:
    """Width of the first image file in ``folder`` (its header only), or None."""
    import OpenImageIO as oiio

    if not folder.is_dir():
        return None
    for p in sorted(folder.iterdir()):
        if p.suffix in IMAGE_EXTS:
            inp = oiio.ImageInput.open(str(p))
            if inp is not None:
                try:
                    return int(inp.spec().width)
                finally:
                    inp.close()
    return None


def _graphdeco_width(resolution, width0: Optional[int]) -> Optional[int]:
    """The training width graphdeco's ``--resolution`` gives images ``width0`` wide."""
    if width0 is None:
        return None
    r = -1 if resolution is None else resolution
    if r in (1, 2, 4, 8):
        return int(round(width0 / r))
    if r == -1:     # (as graphdeco computes it: through the downscale factor, truncated)
        return int(width0 / (width0 / 1600)) if width0 > 1600 else None
    return int(width0 / (width0 / float(r)))


def _resolve(p: Optional[str], *bases: Path) -> Optional[Path]:
    if not p:
        return None
    q = Path(str(p)).expanduser()
    if q.is_absolute():
        return q if q.is_dir() else None
    for b in bases:
        if (b / q).is_dir():
            return (b / q).resolve()
    return q.resolve() if q.is_dir() else None


# ----------------------------------------------------------------------------- the sources
@dataclass
class _Source:
    """What a layout's files say: the scene, the record, the candidate frames, the capture and the
    tool's defaults."""

    scene: GaussianScene
    info: dict
    candidates: list = field(default_factory=lambda: [("the capture's own frame", Similarity())])
    cameras: Optional[Cameras] = None         # the source's own cameras (graphdeco cameras.json)
    data_dir: Optional[Path] = None
    split: int = 8
    background: tuple = (1.0, 1.0, 1.0)
    images: str = "images"
    width: Optional[int] = None


def _graphdeco(source: Path, data_dir: Optional[Path], iteration, images, width) -> _Source:
    if not source.is_dir():
        raise InputError(f"{source}: a graphdeco output is a folder (with point_cloud/iteration_N)")
    g = graphdeco_folder(source, iteration)
    src = _Source(read_ply(g.ply), dict(file=str(g.ply), iteration=g.iteration, cfg_args=g.cfg or None),
                  split=8 if g.cfg.get("eval") else 0, images=g.cfg.get("images") or "images",
                  background=(1.0, 1.0, 1.0) if g.cfg.get("white_background") else (0.0, 0.0, 0.0))
    if data_dir is None:
        data_dir = _resolve(g.cfg.get("source_path"), source, source.parent)
        if data_dir is None and g.cfg.get("source_path"):
            log.warning("the capture %s that cfg_args names is not here: importing cameras.json's cameras "
                        "without images (no PSNR; pass --data to measure it)", g.cfg.get("source_path"))
    src.data_dir = data_dir
    if g.cameras is not None:
        try:
            src.cameras = graphdeco_cameras(g.cameras, str(source / "cameras.json"))
        except InputError as e:
            if data_dir is None:      # the run's only cameras
                raise
            log.warning("%s; the capture's cameras are used as they are", e)
    if width is None and data_dir is not None:
        src.width = _graphdeco_width(g.cfg.get("resolution"), _image_width(data_dir / (images or src.images)))
    return src


def _gsplat(source: Path, data_dir: Optional[Path], iteration) -> _Source:
    cfg = _cfg_yml(source if source.is_dir() else source.parent.parent)
    if source.is_dir():
        ckpts = gsplat_checkpoints(source)
        plys = {int(m.group(1)): p for p in (source / "ply").glob("point_cloud_*.ply")
                if (m := re.fullmatch(r"point_cloud_(\d+)\.ply", p.name))}
        pool = ckpts or plys
        if not pool:
            raise InputError(f"{source}: no ckpts/ckpt_*.pt nor ply/point_cloud_*.ply")
        step = max(pool) if iteration is None else iteration
        if step not in pool:
            raise InputError(f"{source}: no step {step} (it holds {', '.join(map(str, sorted(pool)))})")
        file = pool[step]
    else:
        file, step = source, None
    if file.suffix == ".pt":
        scene, step2 = read_gsplat_checkpoint(file)
        step = step if step is not None else step2
    else:
        scene = read_splat_file(file)
    factor = int(cfg.get("data_factor", 1) or 1)
    if data_dir is None and cfg.get("data_dir"):
        data_dir = _resolve(str(cfg["data_dir"]), source if source.is_dir() else source.parent)
    if data_dir is None:
        raise InputError(f"{source}: a gsplat result does not hold its capture: pass --data with the COLMAP "
                         f"folder it was trained on")
    return _Source(scene, dict(file=str(file), step=step), data_dir=data_dir, split=int(cfg.get("test_every", 8)),
                   images=f"images_{factor}" if factor > 1 else "images")


def _nerfstudio(source: Path, data_dir: Optional[Path], dp: Optional[Path]) -> _Source:
    if source.suffix.lower() != ".ply":
        raise InputError(f"{source}: expected the PLY of `ns-export gaussian-splat`")
    dp = dp or source.parent / "dataparser_transforms.json"
    if not dp.is_file():
        raise InputError(f"{dp}: not found (pass --dataparser-transforms with the training run's "
                         f"dataparser_transforms.json, e.g. outputs/NAME/splatfacto/DATE/)")
    if data_dir is None:
        raise InputError(f"{source}: pass --data with the nerfstudio dataset folder (its transforms.json)")
    tj = data_dir / "transforms.json"
    if tj.is_file():          # nerfstudio-data: the transforms.json frame (applied_transform of the original)
        meta = read_json(tj)
        meta = meta if isinstance(meta, dict) else {}
        sim = nerfstudio_to_capture(dp, meta, colmap_in_dataset=(data_dir / "colmap" / "sparse" / "0").is_dir())
        plain = nerfstudio_to_capture(dp, {k: v for k, v in meta.items() if k != "applied_transform"})
        cands = [("nerfstudio's dataparser frame", sim)]
        if not np.allclose(plain.matrix, sim.matrix):   # (older exports: no applied_transform taken into account)
            cands.append(("nerfstudio's dataparser frame without applied_transform", plain))
    elif find_model(data_dir) is not None:   # the colmap dataparser: its saved transform starts from COLMAP's frame
        cands = [("nerfstudio's dataparser frame (COLMAP data)", nerfstudio_to_capture(dp))]
    else:
        raise InputError(f"{data_dir}: no transforms.json nor COLMAP model (the dataset splatfacto was trained on)")
    return _Source(read_splat_file(source), dict(file=str(source), dataparser_transforms=str(dp)), cands,
                   data_dir=data_dir)


def _frames_of(src: _Source, tool: str, capture: SceneData) -> list:
    """The candidate frames given the loaded capture: graphdeco's cameras.json aligned to it; gsplat's
    normalised world of a COLMAP capture (first for gsplat, after the capture's own for a bare PLY)."""
    cands = list(src.candidates)
    if src.cameras is not None:
        pairs = match_names(src.cameras.names, capture.names)
        if len(pairs) >= 3:
            a = src.cameras.centers.double().numpy()[[i for i, _ in pairs]]
            b = capture.cameras.centers.double().numpy()[[j for _, j in pairs]]
            fit = umeyama(a, b)
            if not np.allclose(fit.matrix, np.eye(4), atol=1e-5 * max(1.0, float(np.abs(b).max()))):
                cands.append(("aligned by cameras.json's camera centres", fit))
    if tool in ("gsplat", "ply") and capture.format == "colmap":
        model = read_model(find_model(capture.data_dir))
        if model.points is not None and len(model.points) >= 3:
            ims = sorted(model.images.values(), key=lambda im: im.name)
            c2w = np.linalg.inv(np.stack([im.viewmat for im in ims]))
            norm = [(lab, s.inverse()) for lab, s in gsplat_normalization(c2w, model.points.xyz)]
            cands = norm + cands if tool == "gsplat" else cands + norm
    return cands


def _cameras_only(cams: Cameras, split: int, bg) -> SceneData:
    n = len(cams)
    test = [i for i in range(n) if split and i % split == 0]
    train = [i for i in range(n) if i not in set(test)]
    if not train:
        train, test = list(range(n)), []
    return SceneData(cameras=cams, images=torch.zeros(n, cams.height, cams.width, 3), names=list(cams.names),
                     train_ids=train, test_ids=test, background=bg, data_dir=None, format="graphdeco-cameras",
                     options=dict(split_every=split, background=list(bg)))


# ----------------------------------------------------------------------------- the stage
@dataclass(frozen=True)
class ImportConfig:
    """How ``ssgwarp import`` reads splats trained elsewhere: its options by name.

    ``data``: the capture (default: the one the source records, where it records one); ``tool``: graphdeco,
    gsplat, nerfstudio or ply (default: detected); ``iteration``: the source's checkpoint (default: its last);
    ``images`` / ``width``: the capture's image folder and training width (default: the source tool's);
    ``split_every``: hold out every N-th view (default: the tool's split: graphdeco's ``eval`` every 8th or none,
    gsplat's ``test_every``, otherwise 8); ``background``: default the tool's (graphdeco: black unless
    ``white_background``; others white); ``dataparser_transforms``: nerfstudio's file (default: found next to the
    source). A splat file without ``data``: a run with ``views`` cameras made around its splats
    (:func:`ssgwarp.services.runs.write_orbit_run`; ``up``: its ``--up``, ``width`` its width, ``seed``), no PSNR."""

    data: Optional[str | Path] = None
    tool: Optional[str] = None
    iteration: Optional[int] = None
    images: Optional[str] = None
    width: Optional[int] = None
    split_every: Optional[int] = None
    background: Optional[Sequence[float]] = None
    dataparser_transforms: Optional[str | Path] = None
    up: Optional[str] = None
    views: int = 24
    seed: int = 0


def import_splats(source: str | Path, out: str | Path, config: ImportConfig = ImportConfig(), *, force: bool = False,
                  device=None, progress: bool = True) -> dict:
    """Import ``source`` into the run folder ``out`` as ``config`` says (see the module docs and
    :class:`ImportConfig`); returns the metrics dict. ``force``: replace an existing run."""
    c = config
    data, tool, iteration, images, width, split_every = c.data, c.tool, c.iteration, c.images, c.width, c.split_every
    background, dataparser_transforms, up, views, seed = c.background, c.dataparser_transforms, c.up, c.views, c.seed
    source = Path(source).expanduser()
    out = Path(out).expanduser()
    device = torch.device(device) if device is not None else torch.device("cpu")
    claimed = claim(out, OUTPUTS, force=force, what="a run", resumable=False)
    dp = Path(dataparser_transforms).expanduser() if dataparser_transforms else None
    tool = tool or detect_tool(source, dp)
    if tool not in TOOLS:
        raise InputError(f"--tool {tool}: expected one of {', '.join(TOOLS)}")
    if not source.exists():
        raise InputError(f"{source}: not found")
    data_dir = Path(data).expanduser() if data else None
    if tool == "graphdeco":
        src = _graphdeco(source, data_dir, iteration, images, width)
    elif tool == "gsplat":
        src = _gsplat(source, data_dir, iteration)
    elif tool == "nerfstudio":
        src = _nerfstudio(source, data_dir, dp)
    else:
        if data_dir is None:
            return _import_orbit(source, out, claimed, width=width, up=up, background=background,
                                 views=views, seed=seed)
        src = _Source(read_splat_file(source), dict(file=str(source)), data_dir=data_dir)
    info = {"tool": tool, "source": str(source.resolve()), **src.info}
    split = src.split if split_every is None else split_every
    bg = src.background if background is None else tuple(float(v) for v in background)
    capture, candidates = None, src.candidates
    if src.data_dir is not None:
        capture = load_dataset(src.data_dir, images=images or src.images, split_every=split,
                               width=width if width is not None else src.width, background=bg, num_random_points=1000,
                               init="capture", progress=False)
        candidates = _frames_of(src, tool, capture)
        cams = capture.cameras
    elif src.cameras is not None:
        cams = src.cameras
    else:
        raise InputError(f"{source}: no capture found and no cameras.json: pass --data with the capture")

    frame, sim, scene, tried = _choose_frame(src.scene, candidates, capture, cams, bg, device, source, progress)
    info.update(frame=frame, transform=sim.record(), candidates=tried)
    has_images = capture is not None
    capture = capture if capture is not None else _cameras_only(cams, split, bg)
    metrics = _evaluate(scene, capture, bg, device, progress, has_images=has_images)
    metrics["imported"] = info
    claimed.clear()
    write_run(out, scene, capture, metrics, record=dict(imported=tool))
    log.info("wrote %s: %d Gaussians from %s (%s), held-out PSNR %s", out, len(scene), tool, frame,
             "n/a" if metrics["psnr"] is None else f"{metrics['psnr']:.2f} dB")
    return metrics


def _import_orbit(source: Path, out: Path, claimed, *, width, up, background, views: int, seed: int) -> dict:
    """A splat file without its capture: the run of its splats with cameras made around them (no PSNR)."""
    if views < 1:
        raise InputError(f"--views must be >= 1, got {views}")
    scene = read_splat_file(source)
    up_v = parse_up(up)
    bg = (1.0, 1.0, 1.0) if background is None else tuple(float(v) for v in background)
    claimed.clear()
    orbit = write_orbit_run(scene, out, source=source, views=views, width=width, up=up_v, background=bg, seed=seed)
    c = orbit["cameras"]
    metrics = {"num_gaussians": len(scene), "sh_degree": scene.sh_degree, "identity_dim": None,
               "resolution": [c["width"], c["height"]], "psnr": None, "ssim": None, "lpips": None,
               "train_psnr": None, "test_views": 0, "per_view": [],
               "note": "no capture: cameras made around the splats (data.json's orbit); pass --data to import "
                       "against the capture and measure PSNR",
               "imported": {"tool": "splat file", "source": str(source.resolve()),
                            "frame": "the file's own (no capture: cameras made around the splats)"}}
    write_json(out / "metrics.json", metrics)
    log.info("wrote %s: %d Gaussians, no capture: %d cameras made around them at %dx%d", out, len(scene), views,
             c["width"], c["height"])
    return metrics


def _evaluate(scene: GaussianScene, data: SceneData, bg, device, progress: bool, has_images: bool) -> dict:
    m: dict = {"num_gaussians": len(scene), "sh_degree": scene.sh_degree, "identity_dim": None,
               "resolution": [data.width, data.height], **data.metric_frame, "device": str(device)}
    if not has_images:
        m.update(psnr=None, ssim=None, lpips=None, train_psnr=None, test_views=0, per_view=[],
                 note="no images (the capture was not found): PSNR not measured; pass --data to measure it")
        return m
    per_view, res = [], {}
    for which, ids in (("test", data.test_ids), ("train", data.train_ids)):
        if not ids:
            res[which] = None
            continue
        v = render_views(scene.to(device), data.cameras[ids], bg, depth=False, desc=f"rendering {which} views"
                         if progress else None)
        q = reconstruction_quality(v.rgb.cpu(), data.images[ids].cpu())
        res[which] = q
        per_view += [{"name": data.names[i], "split": which, "psnr": round(p, 3), "ssim": round(s, 4)}
                     for i, p, s in zip(ids, q["psnr"], q["ssim"])]
    mean = lambda q, k: None if q is None else float(np.mean(q[k]))  # noqa: E731
    m.update(psnr=mean(res["test"], "psnr"), ssim=mean(res["test"], "ssim"), lpips=None,
             train_psnr=mean(res["train"], "psnr"), train_ssim=mean(res["train"], "ssim"),
             test_views=len(data.test_ids), per_view=per_view)
    if not data.test_ids:
        m["note"] = "no held-out views (--split-every 0 or the tool trained on every view): train PSNR only"
    return m
