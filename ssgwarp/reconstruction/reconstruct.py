"""3DGS reconstruction of a capture (the ``ssgwarp reconstruct`` command: :mod:`ssgwarp.commands.reconstruct`).

The 3D Gaussian Splatting recipe (Kerbl et al. 2023), one view per step:

* loss ``(1 - 0.2) L1 + 0.2 (1 - SSIM)`` (:func:`ssgwarp.services.losses.photometric`);
* Adam (eps 1e-15), one parameter group per scene tensor with its own learning
  rate; the position rate decays exponentially from ``1.6e-4`` to ``1.6e-6``
  times the scene extent over the run;
* densification by a strategy (:mod:`ssgwarp.reconstruction.strategy`): ``"default"``, the 3DGS
  rules (clone / split by the view-space positional gradient in NDC units, prune
  by opacity and size, opacity reset; at most ``max_gaussians`` Gaussians), or
  ``"mcmc"``, 3DGS-MCMC (relocation of dead Gaussians, growth up to the budget
  ``max_gaussians``, opacity-gated position noise, opacity and scale
  regularisers); its schedule scales with the run's length;
* SH degree raised by one every ``sh_interval`` steps up to ``sh_degree``.

Densification works on every tensor the scene holds (identity encodings
included) and its Adam state, so Gaussian Grouping can train jointly through ``hooks``.

Runs are seeded and repeatable (views, split samples and initial identities
come from dedicated generators), checkpoint atomically to ``OUT/checkpoint.pt``
every ``checkpoint_every`` steps and on Ctrl-C, and resume bit-exactly
(``--resume``). A NaN loss stops the run with the step number; the last good
checkpoint is kept.

The recipe lives in :mod:`ssgwarp.reconstruction.recipe`, the loop in :mod:`ssgwarp.reconstruction.trainer`; this module is
the stage (load, claim the run folder, train, evaluate, write the run files); its command is
:mod:`ssgwarp.commands.reconstruct`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import torch

from ..capture.datasets import load_dataset
from ..services.distributed import SINGLE
from ..errors import SsgwarpError, WeightsNotFound
from ..evaluation.networks import load_lpips
from .recipe import Recipe, options_record, upgrade_record
from .strategy import DefaultStrategy, Strategy
from ..services.runs import RUN_FILES, check_resume, claim, resume_record, write_run
from .trainer import Trainer
from ..services.loop import read_checkpoint

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")

OUTPUTS = (*RUN_FILES, "environment.json")

__all__ = ["OUTPUTS", "ReconstructConfig", "reconstruct"]


# ----------------------------------------------------------------------------- the stage
def _lpips_model(device):
    """LPIPS (found, or downloaded where allowed: :mod:`ssgwarp.services.weights`), or ``(None, reason)``."""
    try:
        return load_lpips(device=device), None
    except WeightsNotFound as e:
        return None, f"skipped: {e}"
    except Exception as e:  # weights present but unusable: report, do not fail the run
        return None, f"skipped: LPIPS weights could not be loaded ({str(e).splitlines()[0] if str(e) else e})"


def _run_metrics(trainer: Trainer, data, scene, device: torch.device, group, seed: int, peaks) -> dict:
    """``metrics.json`` of a finished run: held-out metrics (evaluated here), counts, schedules, memory."""
    lpips, lpips_note = _lpips_model(device)
    ev = trainer.evaluate(lpips=lpips)
    metrics = {
        "psnr": ev["psnr"], "ssim": ev["ssim"], "lpips": ev["lpips"],
        "test_views": ev["views"],
        "num_gaussians": len(scene),
        "train_seconds": round(trainer.elapsed, 2),
        "iters": trainer.step,
        "sh_degree": scene.sh_degree,
        "identity_dim": None if scene.identities is None else int(scene.identities.shape[1]),
        "seed": seed,
        "device": str(device),
        "world_size": group.world_size,
        "batch_size": trainer.batch_size,
        "images_seen": trainer.step * trainer.batch_size,
        "batch_scaling": {"mode": trainer.recipe.batch_scaling, "lr_factor": trainer.lr_factor,
                          "betas": list(trainer.betas)},
        "resolution": [data.width, data.height],
        **data.metric_frame,
        "per_view": ev["per_view"],
    }
    s = trainer.strategy
    metrics["densification"] = {"strategy": s.name, "max_gaussians": s.max_gaussians,
                                "refine_start": s.refine_start, "refine_stop": s.refine_stop,
                                "refine_every": s.refine_every, "reset_every": getattr(s, "reset_every", 0)}
    metrics["backdrop"] = None if trainer.backdrop is None else trainer.backdrop.record()
    metrics["appearance"] = _appearance_record(trainer)
    metrics["eval_protocol"] = trainer.eval_protocol
    metrics["sky"] = trainer.sky_record
    metrics["schedule"] = trainer.schedules.record(trainer.step)
    if ev["views"] == 0:
        metrics["note"] = "no held-out views (split_every=0 or a single image): PSNR/SSIM not measured"
    if lpips_note:
        metrics["lpips_note"] = lpips_note
    if device.type == "cuda" and torch.cuda.is_available():
        metrics["peak_gpu_memory_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
        if peaks is not None:  # every process's peak (they differ by their renders' workspace)
            metrics["peak_gpu_memory_mb_per_rank"] = peaks
    return metrics


def _appearance_record(trainer: Trainer) -> dict:
    """The appearance decision, its evidence and (when on) the fitted transforms in numbers."""
    rec = dict(trainer.appearance_record or {"mode": "auto", "use": False, "why": "not decided"})
    if trainer.appearance is not None:
        rec["fitted"] = trainer.appearance.summary()
    return rec


@dataclass(frozen=True)
class ReconstructConfig:
    """What a reconstruction trains: the options of ``ssgwarp reconstruct`` by name (their defaults are its).

    ``iters``: steps, or ``"auto"``: the 30,000-step schedule until the training views' PSNR stops improving
    (:mod:`ssgwarp.reconstruction.schedules`). ``strategy``: the densification and its knobs, a
    :class:`~ssgwarp.reconstruction.strategy.DefaultStrategy` (``--strategy default``) or
    :class:`~ssgwarp.reconstruction.strategy.MCMCStrategy` (``mcmc``), or its name; its ``max_gaussians`` is
    ``--max-gaussians`` (the cap; mcmc: the budget). ``recipe``: the training knobs every strategy shares
    (:class:`~ssgwarp.reconstruction.recipe.Recipe`, ``sh_degree`` included; default: the 3DGS paper's).
    ``images``, ``split_every``, ``width``, ``max_images``, ``background``, ``num_random_points``, ``init``: how
    the capture is loaded (:func:`~ssgwarp.capture.datasets.load_dataset`; ``init``: ``auto``, ``triangulate``,
    ``random`` or a ``.ply`` path). ``backdrop``, ``appearance``, ``sky``: ``"auto"`` / ``"on"`` / ``"off"``
    (:mod:`~ssgwarp.reconstruction.backdrop`, :mod:`~ssgwarp.reconstruction.appearance`,
    :mod:`~ssgwarp.reconstruction.sky`). ``batch_size``: views per step over all processes (default: one per
    process; on resume, the checkpoint's). ``identity_dim``: identity encodings trained with the scene (grouping
    through ``hooks``)."""

    iters: int | str = "auto"
    strategy: Strategy | str = field(default_factory=DefaultStrategy)
    recipe: Recipe = field(default_factory=Recipe)
    images: str = "images"
    split_every: int = 8
    width: Optional[int] = None
    max_images: Optional[int] = None
    background: Optional[Sequence[float]] = None
    num_random_points: int = 100_000
    init: Any = "auto"
    backdrop: str = "auto"
    appearance: str = "auto"
    sky: str = "auto"
    batch_size: Optional[int] = None
    checkpoint_every: int = 500
    seed: int = 0
    identity_dim: Optional[int] = None


def reconstruct(data_dir: str | Path, out: str | Path, config: ReconstructConfig = ReconstructConfig(), *,
                resume: bool = False, force: bool = False, device=None, progress: bool = True, data=None,
                group=None, hooks: Sequence = (), attach=None, rasterize: Optional[Callable] = None,
                raster_kwargs: Optional[dict] = None) -> dict:
    """Reconstruct the capture in ``data_dir`` into the run folder ``out`` as ``config`` says (what the
    ``reconstruct`` command runs).

    Writes ``out/scene.ply``, ``cameras.json``, ``data.json``, ``metrics.json`` (and ``environment.json`` with a sky;
    keeps ``out/checkpoint.pt``, written every ``config.checkpoint_every`` steps). Existing outputs are never
    overwritten unless ``force`` (which starts over) or ``resume`` (which continues from the checkpoint; a
    checkpoint made with other options that change what it means is refused, naming them).
    ``data`` may be a preloaded :class:`~ssgwarp.capture.datasets.SceneData` of ``data_dir``.
    ``group``: the :class:`ssgwarp.services.distributed.Group` of a data-parallel run (default: alone); only its main
    process writes files and evaluates. ``metrics.json`` and ``data.json`` record the steps run and why the run
    stopped (``schedule``), and the backdrop, appearance and sky decisions with their evidence.
    ``hooks``: :class:`~ssgwarp.reconstruction.trainer.Trainer` hooks; ``attach``: hooks made during the run
    (``reconstruct --groups``); its ``finish(out, metrics, scene) -> dict`` runs once the run files are written
    and what it returns joins ``metrics.json``. ``rasterize``, ``raster_kwargs``: the trainer's renderer.
    Returns the metrics dict (on the other processes: ``{}``).
    """
    c = config
    iters, images, seed = c.iters, c.images, c.seed
    split_every, width, max_images, background, init = c.split_every, c.width, c.max_images, c.background, c.init
    strategy, recipe, batch_size, backdrop, appearance, sky = (c.strategy, c.recipe, c.batch_size, c.backdrop,
                                                                c.appearance, c.sky)
    identity_dim, checkpoint_every, num_random_points = c.identity_dim, c.checkpoint_every, c.num_random_points
    group = group if group is not None else SINGLE
    out = Path(out).expanduser()
    device = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    ckpt = out / "checkpoint.pt"
    claimed = claim(out, OUTPUTS + ("checkpoint.pt",), force=force, resume=resume, what="a reconstruction")
    # load and validate everything before touching the output folder
    if data is None:
        kw = {} if background is None else {"background": background}
        data = load_dataset(data_dir, images=images, split_every=split_every, max_images=max_images, width=width,
                            num_random_points=num_random_points, seed=seed, init=init,
                            progress=progress and group.is_main, **kw)
    state = read_checkpoint(ckpt) if resume and ckpt.is_file() else None
    if state is not None and batch_size is None:
        batch_size = int(state.get("batch_size", 1))
    # what the checkpoint means: a resume with another value of any of these is refused (more --iters is not)
    record = resume_record(**{
        "data": str(Path(data_dir).expanduser().resolve()) if data_dir is not None else None,
        "--images": data.image_dir, "images": list(data.names), "resolution": [data.cameras.width, data.cameras.height],
        "--width": width, "--max-images": max_images, "--split-every": split_every, "--seed": seed,
        "--background": list(data.background) if data.background is not None else None,
        "--init": str(init), "--backdrop": backdrop, "--appearance": appearance, "--sky": sky,      # (--batch-size: the trainer checks it, naming the fix)
        **options_record(recipe, strategy)})      # (--groups: attach.py checks it, naming the fix)
    if state is not None:   # (a record of the flat recipe of earlier versions: upgraded)
        check_resume(upgrade_record(state.get("options")), record, ckpt, "the checkpoint")
    group.barrier()  # everyone has looked at OUT before the main process changes it
    trainer = Trainer(data, iters=iters, recipe=recipe, hooks=hooks, identity_dim=identity_dim, checkpoint_path=ckpt,
                      checkpoint_every=checkpoint_every, rasterize=rasterize, raster_kwargs=raster_kwargs,
                      device=device, seed=seed, progress=progress, strategy=strategy, batch_size=batch_size,
                      group=group, backdrop=backdrop, attach=attach, appearance=appearance, sky=sky)
    trainer.resume_options = record
    if state is not None:
        trainer.load_checkpoint(ckpt, state=state)
        del state
        if trainer.finished:
            log.info("the checkpoint is already at step %d: writing outputs only", trainer.step)
    elif resume:
        if claimed.existing:
            raise SsgwarpError(f"{out}: nothing to resume (no checkpoint.pt); pass --force to start over")
        log.info("no checkpoint in %s: starting from scratch", out)
    if group.is_main:
        claimed.clear()   # (--force: the old run's files)
    if group.is_main:
        out.mkdir(parents=True, exist_ok=True)
    group.barrier()

    if torch.cuda.is_available() and device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    trainer.train()
    peaks = None
    if group.active and device.type == "cuda":
        peaks = [round(v, 1) for v in group.gather(torch.cuda.max_memory_allocated(device) / 2**20)]
    if not group.is_main:
        return {}
    scene = trainer.final_scene()

    metrics = _run_metrics(trainer, data, scene, device, group, seed, peaks)

    if trainer.environment is not None:
        trainer.environment.save(out / "environment.json")
    write_run(out, scene, data, metrics,
              record=dict(seed=seed, backdrop=metrics["backdrop"], appearance=metrics["appearance"], sky=metrics["sky"],
                          schedule={k: v for k, v in metrics["schedule"].items() if k != "stop_rule"}),
              finish=None if attach is None else lambda: attach.finish(out, metrics, scene))
    log.info("wrote %s: %d Gaussians, held-out PSNR %s", out, len(scene),
             "n/a" if metrics["psnr"] is None else f"{metrics['psnr']:.2f} dB")
    return metrics

