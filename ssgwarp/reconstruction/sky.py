"""The sky behind the splats (``reconstruct --sky auto|on|off``): an environment colour field
(:class:`ssgwarp.raster.environment.Environment`, a 16 x 32 latitude-longitude grid of colours) trained with the
scene and composited where the splats leave light through, in place of the constant background.

``auto`` turns it on for captures whose cameras look outward (the backdrop's ``inside-out`` layout,
:func:`ssgwarp.reconstruction.backdrop.camera_layout`: they see the sky all around) and that have no backdrop
(``--backdrop off``, or a scene given): with one, its far shell stands for the sky, and the field measured no gain
(``benchmarks/inside_out.py``); an object or forward-facing capture keeps its background. The grid starts at the training images' mean colour
and has its own Adam learning rate (:data:`LR`). ``metrics.json`` and ``data.json`` record the decision
(``sky``); the run folder gets ``environment.json`` beside ``scene.ply`` (``ssgwarp render`` composites it).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..errors import InputError
from ..raster.environment import Environment
from .backdrop import camera_layout

MODES = ("auto", "on", "off")
LR = 0.01
ROWS, COLS = 16, 32


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError(f"--sky {mode!r}: choose one of {', '.join(MODES)}")
    return mode


def decide(data, mode: str, layout: Optional[str] = None, backdrop: bool = False) -> dict:
    """The decision record (``use``, ``why``, ``layout``); ``backdrop``: whether the run has a backdrop (its far
    shell already stands for the sky: measured, the field then adds nothing)."""
    if mode != "auto":
        return {"mode": mode, "use": mode == "on", "why": f"--sky {mode}"}
    layout = layout or camera_layout(data.cameras[list(data.train_ids)])
    use = layout == "inside-out" and not backdrop
    why = ("the cameras look outward (inside-out) and no backdrop stands for the sky" if use else
           "inside-out, but the backdrop's far shell stands for the sky" if layout == "inside-out" else
           f"the cameras' layout is {layout}: the constant background")
    return {"mode": mode, "use": use, "why": why, "layout": layout}


def initial(data, device) -> Environment:
    """The field at the training images' mean colour (a parameter: ``env.grid.requires_grad``)."""
    mean = torch.stack([data.images[i].reshape(-1, 3).mean(0) for i in data.train_ids]).mean(0)
    env = Environment.constant(mean.cpu(), ROWS, COLS, device=device)
    env.grid = torch.nn.Parameter(env.grid)
    return env
