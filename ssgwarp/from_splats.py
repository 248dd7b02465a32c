"""``ssgwarp stylize FILE`` (:mod:`ssgwarp.commands.stylize`): for a splat file without its capture, the run that
command takes made first (grouping, then stylization: so this module sits
above the stages, as the demo does).

:func:`prepare_source` writes ``OUT/source/``: the file's splats as a reconstruction run with cameras made
around them (:func:`ssgwarp.services.runs.write_orbit_run`: an orbit fitted to the splats, the record in
``OUT/source/data.json`` under ``orbit``), grouped mask-free (:func:`ssgwarp.grouping.stage.group_scene`: there
are no images and no masks, the clusters come from the splats themselves). Key views, Stage 1 (skipped
without its weights, as for any run) and Stage 2 then run on those views as on a reconstruction's, and
``OUT/metrics.json`` names ``OUT/source`` as its source (``ssgwarp render OUT``, ``ssgwarp evaluate OUT``
take it). On ``--resume`` a grouped ``OUT/source`` of the same file and options is kept.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Optional

from .capture.orbit import MAX_WIDTH, VIEWS, parse_up
from .formats.registry import read_splat_file
from .core.fileio import read_image, read_json, write_json
from .errors import InputError

__all__ = ["SOURCE", "prepare_source", "add_record"]

SOURCE = "source"      # the folder in OUT that holds the splat file's run


def _same(src: Path, record: dict) -> bool:
    """Whether ``src`` is a finished, grouped source run made with ``record``'s options."""
    try:
        data = read_json(src / "data.json")
    except (InputError, OSError, ValueError):
        return False
    return (src / "groups" / "groups.json").is_file() and isinstance(data, dict) and \
        (data.get("orbit") or {}).get("options") == record


def prepare_source(file: str | Path, style: str | Path, out: str | Path, outputs, *, views: int = VIEWS,
                   width: Optional[int] = None, max_width: int = MAX_WIDTH, up: Optional[str] = None,
                   group_iters: Optional[int] = None, force: bool = False, resume: bool = False, device="cpu",
                   seed: int = 0, progress: bool = True) -> Path:
    """Make (or, on ``resume``, keep) ``out/source``, the run of the splat file ``file``; returns its path.
    ``outputs``: stylize's own outputs in ``out`` (an existing output is refused unless ``force`` or
    ``resume``, before anything is written)."""
    from .grouping.model import GroupConfig
    from .grouping.stage import group_scene
    from .services.runs import claim, write_orbit_run

    file, out = Path(file).expanduser(), Path(out).expanduser()
    if views < 2:
        raise InputError(f"--views must be >= 2 for a splat file, got {views}")
    read_image(style, 3)                                   # a bad style fails before anything is written
    up_v = parse_up(up)
    claim(out, (*outputs, SOURCE), force=force, resume=resume, what="a stylize output")
    src = out / SOURCE
    record = {"file": str(file.resolve()), "views": views, "width": width, "max_width": max_width,
              "up": up or "auto", "group_iters": group_iters, "seed": seed}
    if resume and _same(src, record):
        if progress:
            print(f"ssgwarp stylize: {src}: the splats' run and groups kept (--resume)", flush=True)
        return src
    scene = read_splat_file(file)
    if src.exists():
        shutil.rmtree(src)
    orbit = write_orbit_run(scene.replace(identities=None), src, source=file, views=views, max_width=max_width,
                            width=width, up=up_v, seed=seed)
    if progress:
        c = orbit["cameras"]
        print(f"ssgwarp stylize: {file.name}: {len(scene)} splats, no capture: {views} cameras made around them "
              f"at {c['width']}x{c['height']} (up: {orbit['fit']['up_rule']}) -> {src}", flush=True)
    cfg = GroupConfig() if group_iters is None else GroupConfig(iters=group_iters)
    info = group_scene(src, masks="none", config=cfg, device=device, seed=seed, progress=progress)
    data = read_json(src / "data.json")
    data["orbit"]["options"] = record
    write_json(src / "data.json", data)
    if progress:
        print(f"ssgwarp stylize: {info['num_groups']} mask-free groups of the splats", flush=True)
    return src


def add_record(out: str | Path, src: Path) -> None:
    """Name the splat file and the made cameras in ``out/metrics.json`` (``splat_file``, ``orbit``)."""
    from .services.runs import update_metrics

    out = Path(out)
    if not (out / "metrics.json").is_file():
        return
    orbit = read_json(src / "data.json").get("orbit") or {}
    update_metrics(out, {"splat_file": orbit.get("source"), "orbit": {k: v for k, v in orbit.items() if k != "options"}})
