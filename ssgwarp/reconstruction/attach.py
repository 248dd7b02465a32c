"""Hooks attached to a :class:`~ssgwarp.reconstruction.trainer.Trainer` while it runs (``Trainer(attach=obj)``;
``reconstruct --groups`` passes one: the grouping layer's labels come from the scene being trained).

The protocol of ``obj``:

* ``prepare(trainer)``: called when the trainer is built, before anything is written: validate, read what
  ``start_at`` needs;
* ``start_at(end) -> step``: the step before which ``obj(trainer) -> hooks`` is called (:func:`attach_hooks`) in a
  run that ends at ``end`` (asked each step until then: ``--iters auto`` may move the end); the scene then
  gets identity encodings of length ``obj.dim`` if it has none (learnt at ``obj.identity_lr`` when it has one,
  else at the recipe's), and the hooks' parameters an optimiser (the Trainer's public
  :meth:`~ssgwarp.reconstruction.trainer.Trainer.add_hooks`: an ``attach`` object is a way of adding hooks while
  the loop runs, the one hook protocol of the Trainer; it reads only the Trainer's public members);
* ``state() -> dict``: what a checkpoint holds of them; ``restore(state) -> hooks``: the hooks back from it
  (:func:`restore_attached`; a checkpoint with attached hooks resumes only with an ``attach``);
* ``finish(out, metrics, scene) -> dict`` (for :func:`ssgwarp.reconstruction.reconstruct.reconstruct`): called
  once the run files are written, with the final scene as written to ``scene.ply`` (on the training device);
  what it returns joins ``metrics.json`` (:func:`ssgwarp.services.runs.write_run`'s ``finish``).
"""
from __future__ import annotations

import inspect
from typing import Optional

from ..errors import InputError


def takes_scene(hook) -> bool:
    """Whether a hook's ``loss`` takes the current scene (a ``scene`` parameter)."""
    try:
        return "scene" in inspect.signature(hook.loss).parameters
    except (TypeError, ValueError):
        return False


def attach_hooks(trainer, state: Optional[dict] = None) -> None:
    """Make ``trainer.attach``'s hooks (from the current scene, or from a checkpoint's ``state``) and add them
    with :meth:`~ssgwarp.reconstruction.trainer.Trainer.add_hooks` (the scene gets identity encodings of
    length ``attach.dim`` when it has none)."""
    obj = trainer.attach
    hooks = obj(trainer) if state is None else obj.restore(state)
    trainer.add_hooks(hooks, identity_dim=int(obj.dim) if state is None else None,
                      identity_lr=getattr(obj, "identity_lr", None), attached=True)


def restore_attached(trainer, state: Optional[dict]) -> set:
    """Give ``trainer`` back the hooks of a checkpoint's ``"attached"`` ``state`` (None: there were none);
    returns the parameter names they add to the scene's (the identities come with the checkpoint)."""
    if state is None:
        return set()
    if trainer.attach is None:
        raise InputError("the checkpoint was trained with hooks attached during the run (reconstruct --groups); "
                         "pass the same options to resume it, or --force to start over")
    if not trainer.attached:
        attach_hooks(trainer, state)
    return {"identities"}
