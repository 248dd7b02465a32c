"""3DGS reconstruction of a capture: ``ssgwarp reconstruct``.

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
the command (``reconstruct``: load, claim the run folder, train, evaluate, write the run files).
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional, Sequence

import torch

from ..services import distributed
from ..capture.datasets import check_init, load_dataset
from ..services.distributed import SINGLE
from ..errors import InputError, SsgwarpError, WeightsNotFound
from ..evaluation.networks import load_lpips
from .recipe import Recipe
from ..services.runs import RUN_FILES, check_resume, claim, resume_record, write_run
from .schedules import AUTO
from ..core.presets import AtMost
from .trainer import Trainer
from ..services.loop import read_checkpoint

log = logging.getLogger("ssgwarp.reconstruction.reconstruct")

OUTPUTS = (*RUN_FILES, "environment.json")

__all__ = ["OUTPUTS", "reconstruct"]


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
    r = trainer.recipe
    metrics["densification"] = {"strategy": trainer.strategy.name, "max_gaussians": trainer.max_gaussians,
                                "refine_start": r.refine_start, "refine_stop": r.refine_stop,
                                "refine_every": r.refine_every, "reset_every": r.reset_every}
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


def reconstruct(data_dir: str | Path, out: str | Path, *, iters: int | str = "auto", images: str = "images",
                sh_degree: int = 3, max_gaussians: int = 1_000_000, resume: bool = False, force: bool = False,
                device=None, seed: int = 0, hooks: Sequence = (), identity_dim: Optional[int] = None,
                split_every: int = 8, width: Optional[int] = None, max_images: Optional[int] = None,
                background: Optional[Sequence[float]] = None, recipe: Optional[Recipe] = None,
                checkpoint_every: int = 500, num_random_points: int = 100_000,
                rasterize: Optional[Callable] = None, raster_kwargs: Optional[dict] = None,
                progress: bool = True, data=None, strategy="default", batch_size: Optional[int] = None,
                group=None, init="auto", backdrop: str = "auto", attach=None, appearance: str = "auto",
                sky: str = "auto") -> dict:
    """Reconstruct the capture in ``data_dir`` into the run folder ``out`` (what the CLI runs).

    Writes ``out/scene.ply``, ``cameras.json``, ``data.json``, ``metrics.json`` (and keeps
    ``out/checkpoint.pt``). Existing outputs are never overwritten unless ``force``
    (which starts over) or ``resume`` (which continues from the checkpoint).
    ``data`` may be a preloaded :class:`~ssgwarp.capture.datasets.SceneData` of ``data_dir``.
    ``batch_size``: views per step over all processes (default: one per process; on
    ``resume``, the checkpoint's). ``group``: the :class:`ssgwarp.services.distributed.Group` of a
    data-parallel run (default: alone); only its main process writes files and evaluates. ``init``: the
    initial points (:func:`~ssgwarp.capture.datasets.load_dataset`'s: ``auto``, ``triangulate``, ``random`` or a
    ``.ply`` path).
    ``backdrop``: ``"auto"`` / ``"on"`` / ``"off"``, far points and a far shell for what lies beyond the
    initial points (:mod:`ssgwarp.reconstruction.backdrop`); the decision goes to ``metrics.json`` and
    ``data.json`` (``backdrop``).
    ``iters``: steps, or ``"auto"`` (the default): the 30,000-step schedule until the training views' PSNR stops
    improving (:mod:`ssgwarp.reconstruction.schedules`); ``metrics.json`` and ``data.json`` record the steps run and why
    the run stopped (``schedule``).
    ``appearance``: ``"auto"`` / ``"on"`` / ``"off"``, per-image exposure and white balance
    (:mod:`ssgwarp.reconstruction.appearance`); the decision and its evidence go to ``metrics.json`` and ``data.json``
    (``appearance``), and how held-out views were scored to ``metrics.json`` (``eval_protocol``).
    ``sky``: ``"auto"`` / ``"on"`` / ``"off"``, an environment colour field behind the splats
    (:mod:`ssgwarp.reconstruction.sky`), written to ``out/environment.json`` when on; the decision goes to
    ``metrics.json`` and ``data.json`` (``sky``).
    ``attach``: hooks made during the run (:class:`~ssgwarp.reconstruction.trainer.Trainer`'s ``attach``;
    ``reconstruct --groups``); its ``finish(out, metrics, scene) -> dict`` runs once the run files are written
    and what it returns joins ``metrics.json``.
    Returns the metrics dict (on the other processes: ``{}``).
    """
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
        "--sh-degree": sh_degree, "--max-gaussians": max_gaussians,
        "--strategy": strategy if isinstance(strategy, str) else getattr(strategy, "name", str(strategy)),
        "--background": list(data.background) if data.background is not None else None,
        "--init": str(init), "--backdrop": backdrop, "--appearance": appearance, "--sky": sky,      # (--batch-size: the trainer checks it, naming the fix)
        **_recipe_record(recipe)})      # (--groups: attach.py checks it, naming the fix)
    if state is not None:
        check_resume(state.get("options"), record, ckpt, "the checkpoint")
    group.barrier()  # everyone has looked at OUT before the main process changes it
    trainer = Trainer(data, iters=iters, sh_degree=sh_degree, max_gaussians=max_gaussians, recipe=recipe,
                      hooks=hooks, identity_dim=identity_dim, checkpoint_path=ckpt,
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


def _recipe_record(recipe: Optional[Recipe]) -> dict:
    """The recipe's part of the resume record: its command-line options by name, the rest as ``recipe``."""
    r = asdict(recipe if recipe is not None else Recipe())
    return {"--coarse-to-fine": r.pop("res_start", None), "--batch-scaling": r.pop("batch_scaling", None), "recipe": r}


# ----------------------------------------------------------------------------- CLI
def _background(s: str) -> tuple[float, float, float]:
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
    if s in named:
        return named[s]
    try:
        v = tuple(float(x) for x in s.split(","))
    except ValueError:
        v = ()
    if len(v) != 3:
        raise InputError(f"--background {s!r}: expected white, black or R,G,B in [0, 1]")
    return v  # type: ignore[return-value]


def _iters(s: str) -> int | str:
    if s == AUTO:
        return AUTO
    try:
        n = int(s)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{s!r}: expected a number of steps >= 1 or 'auto'")
    return n


def _factor(s: str) -> float:
    try:
        f = float(s)
    except ValueError:
        f = 0.0
    if not f >= 1.0:
        raise argparse.ArgumentTypeError(f"{s!r}: expected a downsampling factor >= 1 (1: off), e.g. 4")
    return f


def add_arguments(parser) -> None:
    parser.add_argument("data_dir", type=Path, help="the capture: COLMAP (sparse/0), LLFF (poses_bounds.npy) "
                        "or NeRF/instant-ngp (transforms*.json) folder")
    parser.add_argument("--out", type=Path, required=True, help="run folder to write")
    parser.add_argument("--iters", type=_iters, default="auto", metavar="N|auto",
                        help="training steps, or auto (default): the 3DGS 30000-step schedule, ended once the PSNR "
                             "of a few training views stops improving (docs/reconstruction.md; hours on a CPU: 7000 "
                             "steps take about 30-50 min for fern images_8 on 2 CPU cores; see --quick)")
    parser.add_argument("--coarse-to-fine", type=_factor, default=1.0, metavar="F",
                        help="train on the images downsampled by F at first, raised to full resolution by the end "
                             "of densification (default 1: off; e.g. 4)")
    parser.add_argument("--images", default="images", help="image sub-folder, e.g. images_4 or images_8 (default images)")
    parser.add_argument("--width", type=int, default=None, help="resize images to this width (default: as loaded)")
    parser.add_argument("--sh-degree", type=int, default=3, help="final SH degree 0..3 (default 3)")
    parser.add_argument("--strategy", choices=("default", "mcmc"), default="default",
                        help="densification: default (3DGS: clone/split/prune, opacity reset) or mcmc "
                             "(3DGS-MCMC: relocation, a fixed budget of --max-gaussians, position noise)")
    parser.add_argument("--max-gaussians", type=int, default=1_000_000,
                        help="cap on the number of Gaussians; with --strategy mcmc the budget it grows to "
                             "(default 1000000)")
    parser.add_argument("--split-every", type=int, default=8,
                        help="hold out every N-th image for testing (default 8, the LLFF convention; 0: none)")
    parser.add_argument("--max-images", type=int, default=None, help="use at most this many images (evenly spaced)")
    parser.add_argument("--background", type=_background, default=None,
                        help="white, black or R,G,B: what RGBA images are composited on (default white)")
    parser.add_argument("--random-points", type=int, default=100_000,
                        help="number of random initial points (--init random, or when triangulation fails; "
                             "default 100000)")
    parser.add_argument("--init", default="auto", metavar="auto|triangulate|random|PATH.ply",
                        help="initial points: auto (default: the capture's COLMAP points, else points "
                             "triangulated from the images and their poses), triangulate (even when the capture "
                             "has points), random, or a .ply point cloud")
    parser.add_argument("--backdrop", choices=("auto", "on", "off"), default="auto",
                        help="far points along the training rays and a far shell (sky) added to the initial "
                             "points: auto (default: when the cameras look outward, or the photos show far "
                             "content where the points leave the images uncovered; docs/reconstruction.md), on "
                             "or off")
    parser.add_argument("--appearance", choices=("auto", "on", "off"), default="auto",
                        help="per-image exposure and white balance (an affine colour transform per training image, "
                             "not part of the scene): auto (default: on when a probe finds the photos' exposures "
                             "differ; docs/reconstruction.md), on or off. When on, held-out views are scored on "
                             "their right half after a colour transform fitted on their left half")
    parser.add_argument("--sky", choices=("auto", "on", "off"), default="auto",
                        help="an environment colour field (a colour per direction, OUT/environment.json) behind the "
                             "splats instead of the constant background: auto (default: on when the cameras look "
                             "outward, an inside-out capture), on or off")
    parser.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints (default 500)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="training views per step, over all processes (default: one per process; on "
                             "--resume the checkpoint's); the default schedule counts images, so --iters N "
                             "--batch-size B trains on N x B images (docs/scaling.md)")
    parser.add_argument("--batch-scaling", choices=("sqrt", "linear", "none"), default="sqrt",
                        help="Adam for batches: learning rates x sqrt(B) (default) or x B with betas ** B, "
                             "or none (one view's settings)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    parser.add_argument("--force", action="store_true", help="overwrite an existing run in OUT")
    parser.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true",
                        help="no progress bar (as the other commands' --quiet)")
    from ..core.presets import add_quick
    add_quick(parser, QUICK, QUICK_MEASURED)


# the CPU-sized preset (`--quick`) and what it cost, measured (README, docs)
QUICK = {"iters": 1500, "width": AtMost(252), "max_gaussians": 60_000}   # (252 px wide at most: never wider)
QUICK_MEASURED = ("fern images_8 (17 training views, resized to 252x188): 20 min on 2 CPU cores shared with other "
                  "work (6.5 min of CPU time), held-out PSNR 26.6 dB, 2026-11-28")


def run(args, **extra) -> int:
    """The command; ``extra`` goes to :func:`reconstruct` (``attach``: ``reconstruct --groups``)."""
    if args.batch_size is not None and args.batch_size < 1:
        raise InputError(f"--batch-size must be >= 1, got {args.batch_size}")
    init = check_init(args.init)
    group, device = distributed.from_env(args.device)  # under torchrun: join the others
    logging.basicConfig(level=logging.INFO if group.is_main else logging.WARNING, format="ssgwarp: %(message)s")
    try:
        m = reconstruct(args.data_dir, args.out, iters=args.iters, images=args.images, sh_degree=args.sh_degree,
                        max_gaussians=args.max_gaussians, resume=args.resume, force=args.force, device=device,
                        seed=args.seed, split_every=args.split_every, width=args.width, max_images=args.max_images,
                        background=args.background, checkpoint_every=args.checkpoint_every,
                        num_random_points=args.random_points, progress=not args.quiet,
                        strategy=args.strategy, batch_size=args.batch_size, backdrop=args.backdrop,
                        appearance=args.appearance, sky=args.sky,
                        recipe=Recipe(batch_scaling=args.batch_scaling, res_start=args.coarse_to_fine),
                        group=group, init=init, **extra)
    finally:
        distributed.shutdown(group)
    if not group.is_main:
        return 0
    ps = "n/a" if m["psnr"] is None else f"{m['psnr']:.2f} dB"
    ss = "n/a" if m["ssim"] is None else f"{m['ssim']:.4f}"
    print(f"{args.out}: {m['num_gaussians']} Gaussians, held-out PSNR {ps}, SSIM {ss}, "
          f"{m['train_seconds']:.0f} s, {m['iters']} steps")
    return 0
