"""A reconstruction's trained state and its checkpoint file: :class:`TrainState`.

:meth:`TrainState.of` takes a :class:`~ssgwarp.reconstruction.trainer.Trainer`'s state (the step, the scene's
tensors and their optimiser, densification statistics, the hooks' parameters and optimiser, the run's own
generators, the stop rule's monitor, the sky and the per-image appearance, the attached hooks' state and the
command's resume record); :meth:`TrainState.save` writes it atomically; :meth:`TrainState.read` reads a file
back (one line naming the file when it is not a checkpoint); :meth:`TrainState.restore` puts it into a
trainer built with the same options, refusing one built with others in one line naming the option to pass
(images, SH degree, strategy, batch size, sky, densification settings, hooks attached during the run).
The file layout (``format`` ``ssgwarp-reconstruct-checkpoint/1``) is unchanged since it was introduced.
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Optional

import torch

from ..core.fileio import atomic_path
from ..errors import InputError
from ..raster.scene import GaussianScene
from ..services.loop import read_checkpoint, to_cpu
from .attach import restore_attached

CHECKPOINT_FORMAT = "ssgwarp-reconstruct-checkpoint/1"

__all__ = ["CHECKPOINT_FORMAT", "TrainState"]


class TrainState:
    """A trainer's state as its checkpoint holds it (``state``: the dict written with :func:`torch.save`)."""

    def __init__(self, state: dict):
        self.state = state

    @property
    def step(self) -> int:
        return int(self.state["step"])

    # -- taking and giving back ---------------------------------------------------------------------
    @classmethod
    def of(cls, t) -> "TrainState":
        """The state of trainer ``t`` (tensors copied to the CPU). The run's own generators only (the
        process-wide RNGs are the caller's: never saved or restored)."""
        rng = {"view": t.view_gen.get_state(), "split": t.strategy.generator_state()}
        return cls({
            "format": CHECKPOINT_FORMAT,
            "step": t.step,
            "iters": t.iters,
            "sh_degree": t.sh_degree,
            "max_gaussians": t.max_gaussians,
            "seed": t.seed,
            "elapsed": t.elapsed,
            "recipe": asdict(t.recipe),
            "strategy": t.strategy.name,
            "strategy_config": asdict(t.strategy),   # (informational, as "recipe": the resolved knobs)
            "batch_size": t.batch_size,
            "world_size": t.group.world_size,  # (informational: any number of processes resumes it)
            "names": list(t.data.names),
            "params": {k: v.detach().cpu() for k, v in t.params.items()},
            "optimizer": to_cpu(t.opt.state_dict()),
            "hook_params": [p.detach().cpu() for p in t._hook_params()],
            "hook_optimizer": to_cpu(t.hook_opt.state_dict()) if t.hook_opt is not None else None,
            "stats": {k: v.detach().cpu() for k, v in t.gaussians.stats.items()},
            "queue": list(t._queue),
            "rng": rng,
            "history": t.history[-1000:],
            "stop_monitor": t.schedules.state_dict(),
            "attached": t.attach.state() if t.attached else None,
            # the resume record of the command that runs this trainer (ssgwarp.services.runs.resume_record)
            "options": getattr(t, "resume_options", None),
            **t.image_model_state(),   # the sky and the per-image appearance (ImageModel)
        })

    def restore(self, t, where: Optional[str | Path] = None) -> None:
        """Put this state into trainer ``t``; refuses one built with other options (one line; ``where``: the
        checkpoint file, named when the state lacks an entry)."""
        try:
            self._restore(t)
        except KeyError as e:
            raise InputError(f"{where or 'the checkpoint'}: checkpoint lacks {e}; use --force to start over") from None

    def _restore(self, t) -> None:
        st = self.state
        if st.get("format") != CHECKPOINT_FORMAT:
            raise InputError(f"not a reconstruction checkpoint (format {st.get('format')!r})")
        if list(st["names"]) != list(t.data.names):
            raise InputError("the checkpoint was trained on other images than this capture's "
                             "(different --images/--max-images?); use --force to start over")
        if int(st["sh_degree"]) != t.sh_degree:
            raise InputError(f"the checkpoint has SH degree {st['sh_degree']}, not {t.sh_degree}; "
                             f"pass --sh-degree {st['sh_degree']} to resume it")
        kind = st.get("strategy", "default")
        if kind != t.strategy.name:
            raise InputError(f"the checkpoint was trained with --strategy {kind}, not {t.strategy.name}; "
                             f"pass --strategy {kind} to resume it")
        b = int(st.get("batch_size", 1))
        if b != t.batch_size:
            raise InputError(f"the checkpoint was trained with --batch-size {b}, not {t.batch_size}; "
                             f"pass --batch-size {b} to resume it (with any number of processes dividing it)")
        saved = set(st["params"])
        if saved != set(t.params) | restore_attached(t, st.get("attached")):
            raise InputError(f"the checkpoint holds {sorted(saved)}, this run {sorted(t.params)}")
        scene = GaussianScene(**{k: v for k, v in st["params"].items()}, sh_degree=t.sh_degree)
        t._build_optimizer(scene.to(t.device))
        t.opt.load_state_dict(st["optimizer"])  # (new group dicts: GaussianParams looks them up by name)
        t._setup_strategy()
        # statistics this run keeps (a checkpoint may hold more, e.g. screen radii of a run that pruned by them)
        stats = {k: v.to(t.device) for k, v in st["stats"].items() if k in t.gaussians.stats}
        if set(stats) != set(t.gaussians.stats):
            raise InputError(f"the checkpoint's densification statistics ({sorted(stats)}) do not match this "
                             f"run's ({sorted(t.gaussians.stats)}): it was written with other densification "
                             f"settings; use --force to start over")
        t.gaussians.stats = stats
        hp = t._hook_params()
        if len(hp) != len(st["hook_params"]):
            raise InputError("the checkpoint's hook parameters do not match this run's hooks")
        with torch.no_grad():
            for p, v in zip(hp, st["hook_params"]):
                p.copy_(v.to(p.device))
        if t.hook_opt is not None and st["hook_optimizer"] is not None:
            t.hook_opt.load_state_dict(st["hook_optimizer"])
        t.step = int(st["step"])
        t.elapsed = float(st.get("elapsed", 0.0))
        t._queue = list(st["queue"])
        rng = st["rng"]
        t.view_gen.set_state(rng["view"])
        t.strategy.set_generator_state(rng["split"])
        t.history = list(st.get("history", []))
        t.load_image_model(st)   # the sky and the per-image appearance (ImageModel)
        t.schedules.load_state_dict(st.get("stop_monitor"))
        t.last_checkpoint_step = t.step

    # -- the file -----------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the checkpoint atomically (a crash leaves the previous one)."""
        path = Path(path)
        with atomic_path(path) as tmp:
            torch.save(self.state, tmp)
        return path

    @classmethod
    def read(cls, path: str | Path) -> "TrainState":
        """The checkpoint at ``path`` (on the CPU), or an InputError naming it."""
        return cls(read_checkpoint(path))
