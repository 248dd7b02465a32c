"""The checkpointed optimisation loop: one policy for every long-running stage.

* **checkpoints**: every ``every`` completed steps and at the end, written atomically by the
  stage's ``save`` callable;
* **Ctrl-C** (SIGINT; SIGTERM too when several processes train together): the step in flight
  finishes, a checkpoint is written and :class:`KeyboardInterrupt` is raised (the CLI exits 130);
  a second Ctrl-C stops at once;
* **an exception inside a step** (a second Ctrl-C, a non-finite loss, an error): the state as of
  the last completed step is saved when the stage can give it (``save_last_good``: for stages
  whose parameters change only at the end of a step), else the last checkpoint is kept; the
  error says which;
* **non-finite losses**: :func:`check_finite` (``torch.isfinite`` on the value, never the text
  of an error) raises :class:`Diverged` with the step and where the last good state is;
* **randomness**: a stage draws from its own :class:`torch.Generator` objects and saves their
  states in its checkpoint; resuming restores those, never the process-wide RNGs.
"""
from __future__ import annotations

import logging
import signal
import threading
from typing import Callable, Optional

import torch
from ..core.progress import tqdm

from ..errors import SsgwarpError

log = logging.getLogger("ssgwarp.services.loop")


class Diverged(SsgwarpError):
    """The loss became NaN or infinite (exit code 2)."""


def check_finite(loss: torch.Tensor, step: int, kept: str, what: str = "the loss") -> None:
    """Raise :class:`Diverged` unless ``loss`` is finite. ``step``: the 1-based step it happened at;
    ``kept``: what the user still has (e.g. ``"the last good checkpoint (step 10) is kept at ..."``)."""
    if not bool(torch.isfinite(loss.detach()).all()):
        raise Diverged(diverged_message(step, kept, what + " is NaN/inf"))


def diverged_message(step: int, kept: str, why: str) -> str:
    return (f"training diverged at step {step} ({why}); {kept}; try a lower learning rate, another --seed, "
            f"or --resume from the checkpoint")


class StopRequest:
    """Ctrl-C as a request: inside ``with StopRequest() as stop:`` the first SIGINT sets
    ``stop.requested``; a second raises :class:`KeyboardInterrupt` (``second_raises``). The handlers
    are installed only in the main thread and restored on exit."""

    def __init__(self, *, sigterm: bool = False, second_raises: bool = True):
        self.requested = False
        self._sigterm = sigterm
        self._second_raises = second_raises
        self._old: dict = {}

    def _on_signal(self, signum, frame) -> None:
        if self.requested and self._second_raises:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            self._old[signal.SIGINT] = signal.signal(signal.SIGINT, self._on_signal)
            if self._sigterm:
                self._old[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._on_signal)
        return self

    def __exit__(self, *exc) -> None:
        for sig, h in self._old.items():
            signal.signal(sig, h)
        self._old.clear()
        self.requested = False


class Loop:
    """Runs ``step_fn`` until ``step_of()`` reaches ``until`` under the policy of the module docs.

    Args:
        step_of: the number of completed steps (the stage advances it in ``step_fn``).
        save: writes a checkpoint of the current (completed-step) state; None: no checkpoints.
        every: steps between checkpoints (0: only on Ctrl-C and at the end).
        save_last_good: writes the state of the last completed step after an exception inside a
            step (None: the last checkpoint is kept).
        stop_agreed: with several processes, whether they agreed to stop this step (the stage
            exchanges the requests; default: this process's own request).
        sigterm / second_raises: for :class:`StopRequest` (several processes: SIGTERM too, and
            a second Ctrl-C waits for the others).
        final_save: write a checkpoint at the end (when ``until`` is reached).
        desc, unit, total, progress: the progress bar. say: log the interruptions (the main process).
        after_stop: called after the Ctrl-C checkpoint (several processes: a barrier).
    """

    def __init__(self, step_of: Callable[[], int], *, save: Optional[Callable[[], None]] = None, every: int = 0,
                 save_last_good: Optional[Callable[[], None]] = None, stop_agreed: Optional[Callable[[], bool]] = None,
                 sigterm: bool = False, second_raises: bool = True, final_save: bool = True,
                 desc: str = "train", unit: str = "step", total: Optional[int] = None, progress: bool = True,
                 after_stop: Optional[Callable[[], None]] = None, say: bool = True):
        self.step_of = step_of
        self.save = save
        self.every = int(every)
        self.save_last_good = save_last_good
        self.stop_agreed = stop_agreed
        self.final_save = final_save
        self.after_stop = after_stop
        self.say = say
        self.request = StopRequest(sigterm=sigterm, second_raises=second_raises)
        self.desc, self.unit, self.total, self.progress = desc, unit, total, progress
        self.saved_step: Optional[int] = None
        self.bar = None

    @property
    def stop_requested(self) -> bool:
        """This process's Ctrl-C request (what a stage sends to the others)."""
        return self.request.requested

    def checkpoint(self) -> None:
        if self.save is not None:
            self.save()
            self.saved_step = self.step_of()

    def run(self, step_fn: Callable[[], Optional[dict]], until: "int | Callable[[], int]",
            on_step: Optional[Callable[[Optional[dict]], None]] = None) -> None:
        """Call ``step_fn`` (one step; returns info for ``on_step``) until ``until`` steps are done
        (``until`` may be a callable, asked after every step: a stage that decides its own end)."""
        if callable(until):
            end = until
        else:
            def end() -> int:
                return until
        total = end() if self.total is None else self.total
        self.bar = tqdm(total=total, initial=self.step_of(), desc=self.desc, unit=self.unit,
                        disable=not self.progress, dynamic_ncols=True)
        clean = False
        try:
            with self.request:
                while self.step_of() < end():
                    info = step_fn()
                    self.bar.update(1)
                    if on_step is not None:
                        on_step(info)
                    step = self.step_of()
                    if self.every > 0 and step % self.every == 0 and step < end():
                        self.checkpoint()
                    stop = self.stop_agreed() if self.stop_agreed is not None else self.request.requested
                    if stop:   # Ctrl-C during this step: it finished cleanly, save it
                        self.checkpoint()
                        if self.save is not None and self.say:
                            log.warning("interrupted at step %d; checkpoint saved (rerun with --resume)", step)
                        if self.after_stop is not None:
                            self.after_stop()
                        clean = True
                        raise KeyboardInterrupt
        except BaseException as e:
            if not clean:
                self._abort(e)
            raise
        finally:
            self.bar.close()
        if self.final_save and self.saved_step != self.step_of():
            self.checkpoint()

    def _abort(self, e: BaseException) -> None:
        """An exception inside a step: save the last completed step when the stage can, else keep the last checkpoint."""
        if self.save_last_good is not None:
            self.save_last_good()
            self.saved_step = self.step_of()
        elif isinstance(e, KeyboardInterrupt) and self.save is not None and self.say:
            log.warning("interrupted inside step %d; the last checkpoint (step %s) is kept", self.step_of() + 1,
                        self.saved_step)


def read_checkpoint(path, what: str = "a reconstruction checkpoint") -> dict:
    """The contents of a checkpoint file (on the CPU; ``what`` it should be), or an :class:`InputError`."""
    from ..errors import InputError

    try:
        st = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(f"{path}: unreadable checkpoint ({str(e).splitlines()[0] if str(e) else type(e).__name__});"
                         f" use --force to start over") from None
    if not isinstance(st, dict):
        raise InputError(f"{path}: not {what}")
    return st


def to_cpu(obj):
    """Tensors in nested dicts and lists detached and on the CPU (an optimizer's state for a checkpoint)."""
    if torch.is_tensor(obj):
        return obj.detach().cpu()
    if isinstance(obj, dict):
        return {k: to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [to_cpu(v) for v in obj]
    return obj
