"""Training Gaussian Grouping's identities and classifier.

:func:`train_identities`: the stage with the geometry frozen (only identities and classifier
are optimised), checkpointed and resumable to the same result under :mod:`ssgwarp.services.loop`'s policy
(every ``checkpoint_every`` steps; Ctrl-C finishes the step and saves; an exception or a
non-finite loss inside a step saves the last completed step, the unfinished one is replayed). :class:`GroupingHook`: joint training with
reconstruction (``ssgwarp group --joint``), as a hook of :class:`ssgwarp.reconstruction.reconstruct.Trainer`.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import torch

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.fileio import atomic_path
from ..core.optim import adam
from ..services.loop import Loop, check_finite
from ..services.runs import check_resume, resume_record
from .model import GroupConfig, init_identities, make_classifier, mask_loss, neighbour_table, regularizer_3d
from ..raster.scene import GaussianScene

Tensor = torch.Tensor


def _adam(identities: Tensor, classifier: torch.nn.Linear, config: GroupConfig) -> torch.optim.Adam:
    return adam([
        {"params": [identities], "lr": config.identity_lr, "name": "identities"},
        {"params": list(classifier.parameters()), "lr": config.classifier_lr, "name": "classifier"},
    ])


def _save_checkpoint(path: Path, step: int, identities: Tensor, classifier: torch.nn.Linear,
                     opt: torch.optim.Optimizer, gen_state: Tensor, meta: dict, history: list,
                     order: list) -> None:
    obj = {"step": step, "identities": identities.detach().cpu(), "classifier": classifier.state_dict(),
           "optimizer": opt.state_dict(), "generator": gen_state, "meta": meta, "history": history,
           "order": list(order)}
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def train_identities(scene: GaussianScene, cameras: Cameras, targets: Tensor, num_groups: int, *,
                     config: GroupConfig = GroupConfig(), seed: int = 0, progress: bool = True,
                     checkpoint_path: Optional[str | Path] = None, resume: bool = False,
                     record: Optional[dict] = None) -> tuple[GaussianScene, torch.nn.Linear, list[dict]]:
    """Train identities and classifier with the geometry frozen.

    Args:
        scene: the reconstructed scene (its geometry and colour are not changed).
        cameras: the C training cameras. targets: ``[C, H, W]`` long masks
        (``IGNORE`` = -1 skipped). num_groups: K.
        checkpoint_path: where checkpoints go (every ``config.checkpoint_every``
        steps and on Ctrl-C); with ``resume`` one of the same setup is continued (its resume record:
        the scene, views, K, dim, seed and settings but ``iters``, plus the caller's ``record``, e.g. the
        masks folder; :func:`ssgwarp.services.runs.check_resume`).
    Returns:
        ``(scene with identities [N, E], classifier, history)``; history holds
        ``{"step", "ce", "reg"}`` every 10 steps (``reg`` None on steps without
        the 3D term). Deterministic for a seed.
    """
    C = len(cameras)
    if targets.shape != (C, cameras.height, cameras.width):
        raise InputError(f"targets must be [C={C}, H={cameras.height}, W={cameras.width}], got {tuple(targets.shape)}")
    dev, dt = scene.device, scene.dtype
    gen = torch.Generator().manual_seed(int(seed))
    geom = scene.detach().replace(identities=None)
    n = len(geom)
    identities = init_identities(n, config.dim, generator=gen, device=dev, dtype=dt).requires_grad_(True)
    classifier = make_classifier(config.dim, num_groups, generator=gen, device=dev, dtype=dt)
    opt = _adam(identities, classifier, config)
    targets = targets.to("cpu", torch.int16 if num_groups < 32767 else torch.long)  # moved per step
    cams = cameras.to(dev)
    table = neighbour_table(geom.means, config)   # (the positions are frozen: one search, not one per step)
    history: list[dict] = []
    order: list[int] = []
    # the resume record (ssgwarp.services.runs): what the checkpoint means; --iters only changes the future
    meta = resume_record(**{"gaussians": n, "--dim": config.dim, "--groups": num_groups, "--seed": int(seed),
                            "views": C, "config": {k: v for k, v in asdict(config).items()
                                                   if k not in ("iters", "checkpoint_every")}, **(record or {})})
    start = 0
    ckpt = Path(checkpoint_path) if checkpoint_path is not None else None
    if resume and ckpt is not None and ckpt.is_file():
        state = torch.load(ckpt, map_location=dev, weights_only=False)
        old = state.get("meta")
        check_resume(old if isinstance(old, dict) and "config" in old else {"setup": old}, meta, ckpt,
                     "the checkpoint")
        with torch.no_grad():
            identities.copy_(state["identities"].to(dev, dt))
        classifier.load_state_dict(state["classifier"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        start = int(state["step"])
        history = list(state["history"])
        order = list(state.get("order", []))
    if num_groups == 1 or C == 0:
        start = config.iters  # nothing to learn: every pixel is group 0

    def next_views() -> list[int]:
        nonlocal order
        out = []
        while len(out) < min(config.views_per_step, C):
            if not order:
                order = torch.randperm(C, generator=gen).tolist()
            out.append(order.pop())
        return out

    prog = {"done": start, "snap": None}    # steps applied; (generator, order) at an unfinished step's start

    def save(step: int, g_state, o) -> None:
        _save_checkpoint(ckpt, step, identities, classifier, opt, g_state, meta, history, o)

    def step_fn() -> None:
        step = prog["done"]
        prog["snap"] = (gen.get_state(), list(order))
        views = next_views()
        s = geom.replace(identities=identities)
        img, _, _ = s.render(cams[views], identities=True, rgb=False)
        logits = classifier(img)
        ce = mask_loss(logits, targets[views].to(dev), num_groups)
        loss = ce
        reg_v = None
        if config.reg_weight > 0 and config.reg_every > 0 and step % config.reg_every == 0:
            reg = regularizer_3d(identities, geom.means, classifier, generator=gen, k=config.reg_k,
                                 samples=config.reg_samples, max_points=config.reg_max_points, neighbours=table)
            loss = loss + config.reg_weight * reg
            reg_v = float(reg.detach())
        check_finite(loss, step + 1, "the last good state is kept in the checkpoint" if ckpt is not None
                     else "no checkpoint path was given")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        prog["done"], prog["snap"] = step + 1, None
        if step % 10 == 0 or step == config.iters - 1:
            history.append({"step": step, "ce": float(ce.detach()), "reg": reg_v})
            loop.bar.set_postfix(ce=f"{float(ce.detach()):.4f}")

    def save_last_good() -> None:
        # an unfinished step is dropped and replayed on resume (same views, same samples): the
        # parameters change only at the end of a step
        g_state, o = prog["snap"] if prog["snap"] is not None else (gen.get_state(), order)
        save(prog["done"], g_state, o)

    loop = Loop(lambda: prog["done"], save=(lambda: save(prog["done"], gen.get_state(), order)) if ckpt else None,
                every=config.checkpoint_every, save_last_good=save_last_good if ckpt else None, final_save=False,
                desc="grouping", unit="it", total=config.iters, progress=progress)
    loop.run(step_fn, config.iters)
    out = scene.detach().replace(identities=identities.detach().clone())
    classifier.requires_grad_(False)
    return out, classifier, history


class GroupingHook:
    """Joint training with reconstruction: a hook for ``ssgwarp.reconstruction.reconstruct.Trainer(..., hooks=[...])``.

    The Trainer renders the identity channels with colour, optimises
    ``scene.identities`` itself and densifies every scene tensor; the hook
    contributes the classifier's parameter group and the grouping loss.

    Args:
        targets: ``[C, H, W]`` long masks, row ``i`` for the Trainer's view index ``i``
            (all-``IGNORE`` rows for views without masks).
        num_groups: K. config: :class:`GroupConfig`. seed: classifier init and
            regulariser samples.
    """

    def __init__(self, targets: Tensor, num_groups: int, *, config: GroupConfig = GroupConfig(), seed: int = 0,
                 device=None, dtype=torch.float32):
        self.config = config
        self.num_groups = int(num_groups)
        self.dim = int(config.dim)
        self.generator = torch.Generator().manual_seed(int(seed) + 7919)
        self.classifier = make_classifier(self.dim, self.num_groups, generator=self.generator,
                                          device=device, dtype=dtype)
        self.targets = targets
        self._last: dict = {}  # the last step's terms, detached on the device (read through ``last``)
        self.history: list[dict] = []   # {"step", "ce", "reg"} every 10 steps (the first view of a step)

    @property
    def last(self) -> dict:
        """The last step's terms as numbers: ``ce`` and, on a step with the 3D term, ``reg`` (None otherwise)."""
        return {"ce": float(self._last["ce"]) if "ce" in self._last else None,
                "reg": float(self._last["reg"]) if "reg" in self._last else None}

    def parameters(self) -> list[dict]:
        """The classifier's Adam parameter group."""
        return [{"params": list(self.classifier.parameters()), "lr": self.config.classifier_lr,
                 "name": "group_classifier"}]

    def loss(self, step: int, view_index: int, identity_render: Tensor, scene: Optional[GaussianScene] = None) -> Tensor:
        """Grouping loss of one rendered view: ``identity_render [H, W, E]`` (or ``[B, H, W, E]``) → scalar."""
        cls = self.classifier
        if cls.weight.device != identity_render.device:
            cls.to(identity_render.device)
        t = self.targets[view_index].to(identity_render.device)
        ce = mask_loss(cls(identity_render), t, self.num_groups)
        loss = ce
        self._last = {"ce": ce.detach()}   # (no host synchronisation per step: read when ``last`` is)
        cfg = self.config
        if scene is not None and scene.identities is not None and cfg.reg_weight > 0 and cfg.reg_every > 0 \
                and step % cfg.reg_every == 0:
            reg = regularizer_3d(scene.identities, scene.means, cls, generator=self.generator, k=cfg.reg_k,
                                 samples=cfg.reg_samples, max_points=cfg.reg_max_points)
            loss = loss + cfg.reg_weight * reg
            self._last["reg"] = reg.detach()
        if step % 10 == 0 and (not self.history or self.history[-1]["step"] != step):
            self.history.append({"step": step, **self.last})
        return loss
