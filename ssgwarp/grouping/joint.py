"""``ssgwarp reconstruct --groups``: Gaussian Grouping trained in the reconstruction's own loop.

One training instead of two: the identity encodings and the group classifier are trained by a
:class:`~ssgwarp.grouping.train.GroupingHook` inside :class:`~ssgwarp.reconstruction.trainer.Trainer`,
attached while it runs (the trainer's ``attach``; the reconstruction layer knows nothing of groups):

* with instance masks (``--masks DIR``, or ``<data_dir>/object_mask``): from step 0 (or ``--group-start``);
* mask-free: for the run's last ``GroupConfig.iters`` steps (the ``group`` stage's 1,000), not before
  densification stops (which counts at most :data:`LATEST_START` of the run), or from ``--group-start``:
  the scene as it is then is clustered (:mod:`ssgwarp.grouping.pseudomasks`) and its labels rendered into
  the training views are the targets of the remaining steps. The start follows the run's end when
  ``--iters auto`` moves it (:meth:`GroupsDuringReconstruction.start_at`).

At the end the run folder holds what ``ssgwarp group`` writes (``groups/groups.json``, the classifier,
group maps, identities in ``scene.ply``), so ``stylize``, ``evaluate``, ``view`` take it unchanged;
``groups.json`` says ``"trained_with": "reconstruct --groups"`` and the step grouping started at.
``ssgwarp group`` stays for scenes reconstructed elsewhere (or imported).

Public API:
    GroupsDuringReconstruction(out, ...)      -> the trainer's ``attach``
    reconstruct_with_groups(data_dir, out, ...) -> metrics dict (groups.json's summary under "groups")
    parse_groups(text)                        -> K or None ("auto")
    (the ``--groups`` options of ``ssgwarp reconstruct``: :mod:`ssgwarp.commands.reconstruct`)
"""
from __future__ import annotations

import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Optional

import torch

from ..core.fileio import write_json
from ..errors import InputError
from ..reconstruction import reconstruct as rec
from ..services.runs import Run, claim
from .mask_files import load_masks, resolve_masks
from .model import FORMAT, GroupConfig
from .pseudomasks import IGNORE, ClusterConfig, pseudo_masks
from .segment import read_record
from .stage import clusters_info, finish_groups, masks_info
from .train import GroupingHook

Tensor = torch.Tensor
TRAINED_WITH = "reconstruct --groups"
LATEST_START = 0.75   # mask-free: densification's stop counts at most this share of the run


def parse_groups(text) -> Optional[int]:
    """``--groups``: ``"auto"`` (None: chosen per scene, or the masks' ids) or an integer K >= 2."""
    if text is None or str(text).lower() == "auto":
        return None
    try:
        k = int(text)
    except (TypeError, ValueError):
        raise InputError(f"--groups {text!r}: give a number of groups K >= 2, or auto") from None
    if k < 2:
        raise InputError(f"--groups {k}: at least 2 groups (or auto); one group is the whole scene, which "
                         f"needs no grouping")
    return k


class GroupsDuringReconstruction:
    """The grouping hook, attached to a reconstruction while it runs (the ``attach`` protocol of
    :class:`~ssgwarp.reconstruction.trainer.Trainer`).

    Args:
        out: the run folder (its ``groups/`` is claimed with ``force``/``resume`` as ``ssgwarp group`` does).
        num_groups: K, or None (the masks' ids; mask-free: chosen per scene up to ``max_groups``).
        masks: a folder of instance masks, ``"auto"`` (``<data_dir>/object_mask`` when present) or None/"none".
        start: the share of the run (0..1) after which grouping starts; None: 0 with masks, mask-free the last
            ``config.iters`` steps, not before densification stops (:meth:`start_at`).
        config: :class:`GroupConfig` (``dim``, learning rates, the 3D regulariser; ``iters``: the steps of
            mask-free grouping).
        cluster: :class:`ClusterConfig` of the mask-free path.
    """

    def __init__(self, out, *, num_groups: Optional[int] = None, masks="auto", max_groups: int = 8,
                 start: Optional[float] = None, config: GroupConfig = GroupConfig(),
                 cluster: Optional[ClusterConfig] = None, ignore_id: Optional[int] = None, seed: int = 0,
                 force: bool = False, resume: bool = False, progress: bool = True):
        if num_groups is not None and num_groups < 2:
            raise InputError(f"--groups {num_groups}: at least 2 groups (or auto)")
        if max_groups < 2:
            raise InputError(f"--max-groups must be >= 2, got {max_groups}")
        if config.dim < 1:
            raise InputError(f"--group-dim must be >= 1, got {config.dim}")
        if start is not None and not 0.0 <= start < 1.0:
            raise InputError(f"--group-start {start}: a share of the run in [0, 1)")
        self.out = Path(out).expanduser()
        self.num_groups, self.masks, self.max_groups, self.share = num_groups, masks, int(max_groups), start
        self.config, self.seed, self.progress = config, int(seed), progress
        self.cluster = replace(cluster or ClusterConfig(), max_groups=int(max_groups))
        self.ignore_id, self.force, self.resume = ignore_id, force, resume
        self.dim = int(config.dim)
        self.identity_lr = config.identity_lr
        self.start, self.refine_stop, self.with_masks = 0, 0, False
        self.targets: Optional[Tensor] = None
        self.k: Optional[int] = None
        self.info: dict = {}
        self.hook: Optional[GroupingHook] = None
        self.claimed = None
        self.seconds = 0.0
        self.device = None

    # -- the attach protocol --------------------------------------------------------------------------------
    def prepare(self, trainer) -> None:
        """Before anything is written: the groups' outputs may be written, the masks are read and checked,
        the start step is set."""
        if trainer.group.active:
            raise InputError("--groups: not with several processes (torchrun) yet; reconstruct on one process "
                             "with --groups, or run `ssgwarp group` on the run afterwards")
        self.claimed = claim(self.out, ("groups/groups.json",), force=self.force, resume=self.resume,
                             what="groups", scratch=("groups/classifier.pt", "groups/group_maps"))
        data = trainer.data
        self.device = trainer.device
        mask_dir = resolve_masks(self.masks, [Path(data.data_dir) / "object_mask"])  # (auto: DATA/object_mask)
        if mask_dir is not None:
            t0 = time.perf_counter()
            made = read_record(mask_dir)   # written by `ssgwarp masks`: instances associated across views
            ignore_id = self.ignore_id if self.ignore_id is not None or made is None else made.get("ignore_id")
            cams = data.cameras
            train = set(data.train_ids)
            ms = load_masks(mask_dir, cams.names, cams.width, cams.height, num_groups=self.num_groups,
                            ignore_id=ignore_id, required=[i in train for i in range(len(cams))],
                            undistortion=None if made is not None else data.undistortion)
            self.targets, self.k = ms.targets, ms.num_groups
            self.info = masks_info(mask_dir, ms, made)
            self.info["test_masks"] = True
            self.seconds += time.perf_counter() - t0
        self.refine_stop = int(trainer.strategy.refine_stop or 0)
        self.with_masks = mask_dir is not None
        self.start = self.start_at(trainer.iters)

    def start_at(self, end: int) -> int:
        """The step grouping starts at in a run that ends at step ``end`` (the trainer asks again when
        ``--iters auto`` moves the end): ``--group-start``'s share of it; 0 with masks; mask-free the last
        ``config.iters`` steps, not before densification stops (counted at most :data:`LATEST_START` of it).
        At least one step trains the groups."""
        end = int(end)
        if self.share is not None:
            start = int(round(self.share * end))
        elif self.with_masks:
            start = 0
        else:
            start = max(min(self.refine_stop, round(LATEST_START * end)), end - int(self.config.iters))
        return max(0, min(int(start), end - 1))

    def __call__(self, trainer) -> list:
        """The hook, from the scene being trained (mask-free: its clusters rendered into the training views)."""
        self.start = int(trainer.step)   # (the step it really started at: --iters auto may have moved it)
        if self.targets is None:
            t0 = time.perf_counter()
            data = trainer.data
            tr = list(data.train_ids)
            scene = trainer.scene.detach()
            images = data.images[tr] if self.cluster.colour == "images" else None
            masks_train, res = pseudo_masks(scene, data.cameras[tr], num_groups=self.num_groups, config=self.cluster,
                                            seed=self.seed, images=images, progress=False)
            targets = torch.full((len(data.cameras), data.height, data.width), IGNORE, dtype=torch.long)
            targets[tr] = masks_train.cpu()
            self.targets, self.k = targets, res.num_groups
            self.info = clusters_info(res, self.cluster)
            self.seconds += time.perf_counter() - t0
        self.hook = GroupingHook(self.targets, self.k, config=self.config, seed=self.seed, device=trainer.device)
        return [self.hook]

    def state(self) -> dict:
        small = torch.int8 if self.k < 127 else torch.int16 if self.k < 32767 else torch.long
        return {"targets": self.targets.to(small), "num_groups": self.k, "info": self.info, "start": self.start,
                "generator": self.hook.generator.get_state(), "history": list(self.hook.history),
                "seconds": self.seconds}

    def restore(self, state: dict) -> list:
        self.targets, self.k = state["targets"].long(), int(state["num_groups"])
        self.info, self.start, self.seconds = dict(state["info"]), int(state["start"]), float(state["seconds"])
        self.hook = GroupingHook(self.targets, self.k, config=self.config, seed=self.seed, device=self.device)
        self.hook.generator.set_state(state["generator"])
        self.hook.history = list(state["history"])
        return [self.hook]

    def finish(self, out: Path, metrics: dict, scene) -> dict:
        """Write the groups of the finished run's ``scene`` (what ``ssgwarp group`` writes; its group maps
        rendered on the scene's device); returns ``{"groups": summary}`` for ``metrics.json``."""
        t0 = time.perf_counter()
        if self.hook is None:
            raise InputError(f"{out}: the reconstruction ended before grouping started (step {self.start} of "
                             f"{metrics.get('iters')}); lower --group-start")
        run = Run.open(out)
        if scene.identities is None or scene.identities.shape[1] != self.dim:
            raise InputError("the reconstruction wrote no identity encodings of the expected length")
        if self.claimed is not None:
            self.claimed.clear()   # (--force: the old groups)
        info = {"format": FORMAT, "dim": self.dim, "seed": self.seed, "joint": True, "trained_with": TRAINED_WITH,
                "start_step": self.start, "iters": metrics.get("iters"), "train_ids": run.train_ids,
                "test_ids": run.test_ids, "config": asdict(self.config), **self.info}
        test_masks = bool(info.pop("test_masks", False))
        info["num_groups"] = info["K"] = self.k
        classifier = self.hook.classifier.to("cpu").requires_grad_(False)
        info = finish_groups(out, run, scene, classifier, self.targets, info, history=self.hook.history,
                             test_masks=test_masks, progress=self.progress)
        info["seconds"] = round(self.seconds + time.perf_counter() - t0, 2)
        write_json(out / "groups" / "groups.json", info)
        ra = info.get("reprojection_agreement", {}).get("mean")
        return {"groups": {"num_groups": self.k, "kind": info["kind"], "start_step": self.start,
                           "train_mask_accuracy": info.get("train_mask_accuracy"), "cross_view_agreement": ra,
                           "seconds": info["seconds"]}}


def reconstruct_with_groups(data_dir, out, reconstruction: rec.ReconstructConfig = rec.ReconstructConfig(), *,
                            num_groups: Optional[int] = None, masks="auto", max_groups: int = 8,
                            group_start: Optional[float] = None, config: GroupConfig = GroupConfig(),
                            cluster: Optional[ClusterConfig] = None, ignore_id: Optional[int] = None,
                            force: bool = False, resume: bool = False, progress: bool = True, **run) -> dict:
    """Reconstruct ``data_dir`` into ``out`` as ``reconstruction`` says, with the groups trained in the same loop
    (``reconstruct --groups``; ``config``: the grouping's knobs, its seed ``reconstruction.seed``).

    ``run`` (``device``, ``data``, ``group``...) goes to :func:`ssgwarp.reconstruction.reconstruct.reconstruct`.
    Returns its metrics, with ``"groups"``: K, the kind of groups, the step grouping started at, mask accuracy,
    cross-view agreement.
    """
    attach = GroupsDuringReconstruction(out, num_groups=num_groups, masks=masks, max_groups=max_groups,
                                        start=group_start, config=config, cluster=cluster, ignore_id=ignore_id,
                                        seed=reconstruction.seed, force=force, resume=resume, progress=progress)
    return rec.reconstruct(data_dir, out, reconstruction, force=force, resume=resume, progress=progress,
                           attach=attach, **run)
