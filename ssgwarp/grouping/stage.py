"""Gaussian Grouping as a stage (``ssgwarp group``): identity encodings and group maps of a run.

Every Gaussian carries an identity vector ``e_i`` (``E = 16`` by default). It
is rendered in the same alpha-blending pass as colour, giving an identity image
``[H, W, E]``; a linear layer ``E -> K`` and a softmax turn it into a group map.
Training (as in Gaussian Grouping):

- 2D: per-pixel cross entropy against instance masks, divided by ``log K``
  (pixels marked ``IGNORE = -1`` do not count);
- 3D: every ``reg_every`` steps, ``reg_samples`` Gaussians are drawn and the KL
  divergence between each one's group distribution and those of its
  ``reg_k`` nearest neighbours (by position) is averaged, divided by K and
  weighted by ``reg_weight``.

Masks come from ``ssgwarp masks`` (:mod:`ssgwarp.grouping.segment`: Segment Anything
instances associated across views, ``RUN/object_mask``), from outside
(``object_mask/<image stem>.png``, integer ids consistent across views) or,
without either, from the scene itself (:mod:`ssgwarp.grouping.pseudomasks`);
``groups.json`` ``kind`` says which. Training runs either as a stage on a
reconstructed scene with geometry frozen (only identities and classifier are
optimised) or jointly with reconstruction (``--joint``, through
:class:`GroupingHook`).

The parts, one module each: the model and losses (:mod:`ssgwarp.grouping.model`), masks from
files (:mod:`ssgwarp.grouping.mask_files`), training (:mod:`ssgwarp.grouping.train`), cross-view
agreement and the plot (:mod:`ssgwarp.grouping.agreement`); this module is the stage on a run
folder and the CLI, and re-exports the parts' public names.

Public API:
    GroupConfig, GroupModel, GroupingHook
    make_classifier(dim, k, generator)             -> nn.Linear
    render_group_maps(scene, cameras, classifier)  -> (labels [C,H,W] long, probs [C,H,W,K])
    gaussian_groups(scene, classifier)             -> (ids [N] long, prob [N])
    mask_loss(logits, targets, k)                  -> scalar
    regularizer_3d(identities, means, classifier)  -> scalar
    load_masks(mask_dir, names, width, height)     -> MaskSet
    train_identities(scene, cameras, targets, k)   -> (scene, classifier, history)
    reprojection_agreement(scene, cameras, labels) -> dict
    group_scene(scene_dir, ...)                    -> summary dict (what the CLI runs)
    load_groups(scene_dir, device)                 -> GroupModel
    (the command: :mod:`ssgwarp.commands.group`)
"""
from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Optional, Sequence

import torch

from ..reconstruction import reconstruct as rec
from ..core.cameras import Cameras
from ..errors import InputError, SsgwarpError
from ..core.fileio import atomic_path, read_json, write_image, write_json
from .agreement import neighbour_pairs, plot_training, reprojection_agreement
from .mask_files import MaskSet, load_masks, read_id_image, resolve_masks
from ..core.imaging import resize_nearest
from .model import FORMAT, GroupConfig
from ..raster.groups import gaussian_groups, group_labels
from .train import GroupingHook, train_identities
from .segment import read_record
from ..core.palette import colorize_labels
from ..formats.ply import read_ply, write_ply
from .pseudomasks import IGNORE, ClusterConfig, pseudo_masks
from ..services.runs import Run, claim
from ..raster.scene import GaussianScene

Tensor = torch.Tensor
# which kind of groups a run used (groups.json "kind")
KINDS = {"segmenter": "segmenter instances", "masks": "given masks", "mask-free": "mask-free clusters"}
# the former private names of the parts (kept importable from here)
_read_id_image, _resize_nearest, _plot = read_id_image, resize_nearest, plot_training

__all__ = ["RunInfo", "KINDS", "map_name", "write_group_outputs", "masks_info", "clusters_info", "finish_groups",
           "group_scene"]


RunInfo = Run   # (the run folder: ssgwarp.services.runs.Run)


def _resolve_masks(masks: Optional[str | Path], run: RunInfo) -> Optional[Path]:
    """``None``/"none" → mask-free; "auto" → ``RUN/object_mask`` (``ssgwarp masks``), else
    ``<data_dir>/object_mask``, when it exists; else the folder given."""
    dd = run.data.get("data_dir")
    return resolve_masks(masks, [run.path / "object_mask"] + ([Path(dd) / "object_mask"] if dd else []))


def _train_images(scene_dir: Path, run: RunInfo, device) -> Optional[Tensor]:
    """The run's training images ``[T, H, W, 3]`` (reloaded from its capture), or None when the capture
    cannot be read (the mask-free path then clusters on the Gaussians' own colours, and says so)."""
    try:
        _, data = run.load()
    except (InputError, OSError):
        return None
    if data.cameras.names != run.cameras.names:
        return None
    return data.images[run.train_ids].to(device)


def _coverage(labels: Tensor, k: int) -> list[float]:
    cnt = torch.bincount(labels.flatten().cpu().long(), minlength=k).double()
    return (cnt / cnt.sum().clamp_min(1)).tolist()


_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp"}


def map_name(name: str) -> str:
    """File stem of a camera's group map: the image name without its image extension, '/' → '_'."""
    p = Path(name)
    base = p.with_suffix("") if p.suffix.lower() in _IMAGE_SUFFIXES else p
    return base.as_posix().replace("/", "_")


def write_group_outputs(scene_dir: Path, scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear,
                        info: dict, *, history: Sequence[dict] = (), progress: bool = True) -> tuple[dict, Tensor]:
    """Write scene.ply (with identities), groups/classifier.pt, groups/groups.json, group maps and the plot.

    Returns the completed ``info`` (per-group Gaussian counts and coverage added)
    and the group maps ``[C, H, W]`` (int16, CPU) of ``cameras``.
    """
    k = classifier.out_features
    gdir = scene_dir / "groups"
    labels = group_labels(scene, cameras, classifier, progress=progress)
    ids, prob = gaussian_groups(scene, classifier)
    counts = torch.bincount(ids.cpu(), minlength=k).tolist()
    train_ids = info.get("train_ids", list(range(len(cameras))))
    cover_train = _coverage(labels[train_ids], k) if train_ids else _coverage(labels, k)
    info["groups"] = [{"id": g, "gaussians": int(counts[g]), "screen_coverage": float(cover_train[g]),
                       "mean_probability": float(prob[ids == g].mean()) if counts[g] else None}
                      for g in range(k)]
    info["groups_present"] = int(sum(1 for g in info["groups"] if g["gaussians"] > 0 or g["screen_coverage"] > 0))
    write_ply(scene_dir / "scene.ply", scene.detach().to("cpu"))
    with atomic_path(gdir / "classifier.pt") as tmp:
        torch.save({"format": FORMAT, "dim": classifier.in_features, "num_groups": k,
                    "state_dict": {n: t.detach().cpu() for n, t in classifier.state_dict().items()}}, tmp)
    for i, name in enumerate(cameras.names):
        write_image(gdir / "group_maps" / f"{map_name(name)}.png",
                    colorize_labels(labels[i], k))
    info["outputs"] = {"classifier": "groups/classifier.pt", "group_maps": "groups/group_maps/",
                       "plot": "groups/groups.png", "scene": "scene.ply"}
    write_json(gdir / "groups.json", info)
    plot_training(gdir / "groups.png", info.get("criterion"), list(history),
          f"{scene_dir.name}: K={k} ({str(info.get('method')).split(' (')[0]})")
    return info, labels


def group_scene(scene_dir: str | Path, *, masks: Optional[str | Path] = "auto", num_groups: Optional[int] = None,
                max_groups: int = 8, joint: bool = False, config: GroupConfig = GroupConfig(),
                cluster: Optional[ClusterConfig] = None, ignore_id: Optional[int] = None, force: bool = False,
                resume: bool = False, device=None, seed: int = 0, progress: bool = True,
                reconstruct_kwargs: Optional[dict] = None) -> dict:
    """Group a reconstructed run (what ``ssgwarp group`` runs); returns the groups.json content.

    ``masks``: a folder of instance masks, "auto" (``<data_dir>/object_mask``
    when present, else mask-free) or None/"none" (mask-free).
    """
    t0 = time.time()
    scene_dir = Path(scene_dir)
    run = Run.open(scene_dir)
    gdir = scene_dir / "groups"
    claimed = claim(scene_dir, ("groups/groups.json",), force=force, resume=resume, what="groups",
                    scratch=("groups/checkpoint.pt", "groups/classifier.pt", "groups/group_maps"))
    if num_groups is not None and num_groups < 1:
        raise InputError(f"--groups must be >= 1, got {num_groups}")
    if max_groups < 1:
        raise InputError(f"--max-groups must be >= 1, got {max_groups}")
    if config.dim < 1:
        raise InputError(f"--dim must be >= 1, got {config.dim}")
    device = torch.device(device) if device is not None else torch.device("cpu")
    scene = read_ply(scene_dir / "scene.ply", device=device)
    scene = scene.replace(identities=None)
    cams = run.cameras
    train_cams = cams[run.train_ids]
    mask_dir = _resolve_masks(masks, run)
    info: dict = {"format": FORMAT, "dim": config.dim, "seed": int(seed), "joint": bool(joint),
                  "train_ids": run.train_ids, "test_ids": run.test_ids,
                  "config": asdict(config)}
    if mask_dir is not None:
        made = read_record(mask_dir)        # written by `ssgwarp masks`: instances associated across views
        if made is not None and ignore_id is None:
            ignore_id = made.get("ignore_id")
        ms = load_masks(mask_dir, cams.names, cams.width, cams.height, num_groups=num_groups, ignore_id=ignore_id,
                        required=[i in set(run.train_ids) for i in range(len(cams))],
                        undistortion=None if made is not None else run.data.get("undistortion"))
        k = ms.num_groups
        all_targets = ms.targets
        info.update(masks_info(mask_dir, ms, made))
    else:
        ccfg = cluster if cluster is not None else ClusterConfig(max_groups=max_groups)
        if cluster is not None and cluster.max_groups != max_groups:
            ccfg = ClusterConfig(**{**asdict(cluster), "max_groups": max_groups})
        images = _train_images(scene_dir, run, device) if ccfg.colour == "images" else None
        masks_train, res = pseudo_masks(scene, train_cams, num_groups=num_groups, config=ccfg, seed=seed,
                                        images=images, progress=progress)
        k = res.num_groups
        all_targets = torch.full((len(cams), cams.height, cams.width), IGNORE, dtype=torch.long)
        all_targets[run.train_ids] = masks_train.cpu()
        info.update(clusters_info(res, ccfg))
    info["num_groups"] = k
    info["K"] = k
    history: list[dict] = []
    claimed.clear()   # (--force, everything read and checked: the old groups and any checkpoint)
    if joint:
        scene, classifier, extra = _joint(scene_dir, run, all_targets, k, config, seed, device, progress,
                                          reconstruct_kwargs or {}, resume=resume)
        info["joint_reconstruction"] = extra
    else:
        scene, classifier, history = train_identities(
            scene, train_cams, all_targets[run.train_ids], k, config=config, seed=seed, progress=progress,
            checkpoint_path=gdir / "checkpoint.pt", resume=resume,
            record={"--masks": str(mask_dir.resolve()) if mask_dir is not None else "none"})
    info = finish_groups(scene_dir, run, scene, classifier, all_targets, info, history=history,
                         test_masks=mask_dir is not None, progress=progress)
    info["seconds"] = round(time.time() - t0, 2)
    write_json(gdir / "groups.json", info)
    ck = gdir / "checkpoint.pt"
    if ck.is_file():
        ck.unlink()
    return info


def masks_info(mask_dir: Path, ms: MaskSet, made: Optional[dict]) -> dict:
    """groups.json's record of groups trained on the masks ``ms`` read from ``mask_dir`` (``made``: the
    folder's ``ssgwarp masks`` record, or None)."""
    info = {"method": "masks", "mask_dir": str(mask_dir), "mask_ids": ms.ids, "criterion": None,
            "kind": KINDS["segmenter" if made and made.get("source", {}).get("kind") == "segmenter" else "masks"]}
    if made is not None:
        info["masks_record"] = {"source": made.get("source"), "num_instances": made.get("num_instances"),
                                "ignore_id": made.get("ignore_id"), "record": str(mask_dir.parent / "masks.json")}
    return info


def clusters_info(res, ccfg: ClusterConfig) -> dict:
    """groups.json's record of mask-free groups (the clustering's :class:`ClusterResult` ``res``)."""
    crit = dict(res.criterion)
    crit["values"] = {int(a): float(b) for a, b in crit.get("values", {}).items()}
    return {"method": "mask-free (spectral clustering of the Gaussians on position, colour, shape; "
                      "K by log-eigengap)", "kind": KINDS["mask-free"], "criterion": crit,
            "cluster_config": asdict(ccfg)}


def finish_groups(scene_dir: Path, run: RunInfo, scene: GaussianScene, classifier: torch.nn.Linear,
                  all_targets: Tensor, info: dict, *, history: Sequence[dict] = (), test_masks: bool = False,
                  progress: bool = True) -> dict:
    """Write the groups of a trained scene (:func:`write_group_outputs`) and score them: how well the group
    maps reproduce the training targets ``all_targets [C, H, W]`` (and the held-out ones, ``test_masks``),
    how well they agree across views. Returns ``info`` completed (the caller writes groups.json)."""
    cams = run.cameras
    info["history_tail"] = list(history)[-5:]
    info, labels = write_group_outputs(scene_dir, scene, cams, classifier, info, history=history, progress=progress)
    tr = run.train_ids
    t = all_targets[tr]
    valid = t >= 0
    info["train_mask_accuracy"] = float((labels[tr].cpu()[valid] == t[valid]).double().mean()) if bool(valid.any()) else None
    if run.test_ids and test_masks:
        tt = all_targets[run.test_ids]
        v = tt >= 0
        info["test_mask_accuracy"] = float((labels[run.test_ids].cpu()[v] == tt[v]).double().mean()) if bool(v.any()) else None
    info["reprojection_agreement"] = reprojection_agreement(scene, cams, labels, neighbour_pairs(cams))
    return info


def _joint(scene_dir: Path, run: RunInfo, targets: Tensor, k: int, config: GroupConfig, seed: int, device,
           progress: bool, kwargs: dict, resume: bool = False):
    """Re-run reconstruction of the run's capture with a :class:`GroupingHook` (replaces the run's scene).

    The capture is reloaded through :meth:`ssgwarp.services.runs.Run.load`, so the
    Trainer's view indices are the rows of ``cameras.json`` (and of ``targets``).
    ``kwargs``: fields of its :class:`~ssgwarp.reconstruction.reconstruct.ReconstructConfig` (``iters``,
    ``recipe``, ``strategy``...); by default the original run's iteration count and SH degree are reused (the
    SH degree also with a ``recipe`` given; ``sh_degree``: another).
    """
    _, data = run.load()
    if data.cameras.names != run.cameras.names:
        raise SsgwarpError(f"{scene_dir}: the reloaded capture's views do not match cameras.json")
    metrics = read_json(scene_dir / "metrics.json") if (scene_dir / "metrics.json").is_file() else {}
    kw = {"iters": int(metrics.get("iters", 30000))}
    kw.update({k_: v for k_, v in kwargs.items() if v is not None})
    sh = kw.pop("sh_degree", None)
    kw["recipe"] = replace(kw.get("recipe") or rec.Recipe(),
                           sh_degree=int(sh if sh is not None else metrics.get("sh_degree", 3)))
    hook = GroupingHook(targets, k, config=config, seed=seed, device=device)
    cfg = rec.ReconstructConfig(**kw, identity_dim=config.dim, seed=seed)
    metrics = rec.reconstruct(data.data_dir, scene_dir, cfg, hooks=[hook], device=device, progress=progress, data=data,
                              force=not resume, resume=resume)
    scene = read_ply(scene_dir / "scene.ply", device=device)
    if scene.identities is None or scene.identities.shape[1] != config.dim:
        raise SsgwarpError("the joint reconstruction wrote no identity encodings of the expected length")
    summary = {"iters": metrics.get("iters"), "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"),
               "num_gaussians": metrics.get("num_gaussians"), "train_seconds": metrics.get("train_seconds")}
    return scene, hook.classifier.requires_grad_(False), summary
