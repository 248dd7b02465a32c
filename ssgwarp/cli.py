"""The ``ssgwarp`` command: one entry point, one subcommand per pipeline stage.

Each command is a module of :mod:`ssgwarp.commands` providing ``add_arguments(parser)`` and ``run(args) -> int``
(parse, call the library, print); this file only wires them up and turns user errors into one line + exit code 2
(``--debug`` shows the traceback).
"""
from __future__ import annotations

import argparse
import contextlib
import difflib
import importlib
import json
import os
import random
import sys
import traceback
from pathlib import Path
from typing import Optional, Sequence

from .errors import SsgwarpError

# name -> (module, one-line help, examples)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("ssgwarp.commands.demo", "run the whole pipeline on an embedded procedural scene",
             "ssgwarp demo --out ssgwarp-demo"),
    "reconstruct": ("ssgwarp.commands.reconstruct", "3DGS reconstruction of a capture (COLMAP, LLFF, transforms.json); "
                    "--groups also trains Gaussian Grouping in the same loop",
                    "ssgwarp reconstruct data/fern --images images_8 --out runs/fern --iters 7000"),
    "import": ("ssgwarp.commands.import_", "splats trained by graphdeco 3DGS, gsplat, nerfstudio or any 3DGS PLY as a run",
               "ssgwarp import output/garden --out runs/garden"),
    "masks": ("ssgwarp.commands.masks", "instance masks of every training view (Segment Anything), associated across views",
              "ssgwarp masks runs/fern [--sam PATH]"),
    "group": ("ssgwarp.commands.group", "Gaussian Grouping: identity encodings and groups (from masks or mask-free)",
              "ssgwarp group runs/fern [--masks runs/fern/object_mask] [--groups 8]"),
    "keyviews": ("ssgwarp.commands.keyviews", "choose key views and render their RGB, depth and group maps",
                 "ssgwarp keyviews runs/fern --keyviews 4 --out runs/fern/keyviews"),
    "stylize": ("ssgwarp.commands.stylize", "key views, Stage 1 (diffusion + CVSA) and Stage 2 (instance-level style transfer)",
                "ssgwarp stylize runs/fern --style style.jpg --out runs/fern-styled"),
    "evaluate": ("ssgwarp.commands.evaluate", "consistency and style/content metrics of one or more runs",
                 "ssgwarp evaluate runs/fern-styled runs/fern-global"),
    "view": ("ssgwarp.commands.view", "pyvista viewer of a Gaussian cloud, its groups and cameras",
             "ssgwarp view runs/fern/scene.ply --color group --screenshot shot.png"),
    "render": ("ssgwarp.commands.render", "render a scene along its cameras or a smooth path",
               "ssgwarp render runs/fern --out runs/fern/renders [--path]"),
    "export": ("ssgwarp.commands.export", "write a run's scene (or convert a splat file) as PLY, compressed PLY, SPZ, .splat, SOG or GLB",
               "ssgwarp export runs/fern --format spz --out fern.spz [--sh-degree 1]"),
    "weights": ("ssgwarp.commands.weights", "pretrained models: where each is found (or missing), size, licence; "
                "--download fetches them into the Hugging Face / torch hub caches",
                "ssgwarp weights --download stage1 vgg16"),
}


def version() -> str:
    """The installed package's version (its metadata: pyproject.toml's ``version``)."""
    from importlib.metadata import PackageNotFoundError, version as _version

    try:
        return _version("ssgwarp")
    except PackageNotFoundError:       # (a source tree on sys.path without an install)
        from . import __version__
        return __version__


def add_common(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("common")
    g.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (GPU when there is one)")
    g.add_argument("--seed", type=int, default=0, help="random seed (runs are repeatable for a seed)")
    g.add_argument("--config", type=Path, default=None,
                   help="JSON file of option defaults (keys are option names, e.g. {\"iters\": 3000})")
    g.add_argument("--offline", action="store_true",
                   help="never download pretrained weights (as HF_HUB_OFFLINE=1 / SSGWARP_OFFLINE=1); "
                        "stages that can run without them do")
    g.add_argument("--debug", action="store_true", help="show tracebacks")


def resolve_device(name: str):
    import torch

    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SsgwarpError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return dev


def seed_everything(seed: int) -> None:
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def _apply_config(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """Make the ``--config`` file's keys the defaults of the chosen subcommand."""
    if "--config" not in argv:
        return
    i = argv.index("--config")
    if i + 1 >= len(argv):
        return
    path = Path(argv[i + 1])
    if not path.is_file():
        raise SsgwarpError(f"--config {path}: file not found")
    from .core.fileio import read_json

    try:
        cfg = read_json(path)
    except SsgwarpError as e:
        raise SsgwarpError(f"--config {e}") from None
    if not isinstance(cfg, dict):
        raise SsgwarpError(f"--config {path}: expected a JSON object of option defaults")
    # every spelling of an option (dest, or any of its flags without dashes) -> its dest; "weights" is the
    # mapping of model paths every command may take (ssgwarp.services.weights)
    names = {"weights": "weights"}
    for act in parser._actions:
        if act.dest in ("help", "config"):
            continue
        names[act.dest] = act.dest
        for flag in act.option_strings:
            names[flag.lstrip("-").replace("-", "_")] = act.dest
    defaults = {}
    for k, v in cfg.items():
        key = str(k).lstrip("-").replace("-", "_")
        if key not in names:
            near = difflib.get_close_matches(key, list(names), n=1)
            hint = f" (did you mean {near[0].replace('_', '-')!r}?)" if near else ""
            raise SsgwarpError(f"--config {path}: {k!r} is not an option of 'ssgwarp {parser.prog.split()[-1]}'"
                               f"{hint}; see its --help")
        defaults[names[key]] = _config_value(parser, names[key], k, v, path)
    # a preset flag set in the file (``"quick": true``, ``"paint": true``) sets its options as the command line
    # would, below the file's own keys
    from .core.presets import preset_values
    for dest, on in list(defaults.items()):
        if on is True:
            for k, v in preset_values(parser, dest).items():
                defaults.setdefault(k, v)
    parser.set_defaults(**defaults)


def _config_value(parser: argparse.ArgumentParser, dest: str, key: str, v, path: Path):
    """``--config``'s value ``v`` for option ``dest``, converted and checked as the command line would do it
    (the option's type and choices; a switch takes true or false; a list option a list): a wrong value is one
    line naming the file, the key and what the option takes, not a failure deep inside the command."""
    where = f"--config {path}: {key!r}"
    if dest == "weights":
        if not isinstance(v, dict) or not all(isinstance(x, str) for x in [*v.keys(), *v.values()]):
            raise SsgwarpError(f"{where} must map model names to paths (strings)")
        return v
    act = next(a for a in parser._actions if a.dest == dest)
    if act.nargs == 0:                       # a switch (store_true / store_false / a preset)
        if not isinstance(v, bool):
            raise SsgwarpError(f"{where} is a switch: true or false (got {json.dumps(v)[:60]})")
        return v
    many = act.nargs in ("+", "*") or isinstance(act.nargs, int) or isinstance(act, argparse._AppendAction)
    if v is None:
        if act.default is None or act.nargs == "?":
            return None
        raise SsgwarpError(f"{where}: null is not a value of this option")
    if many:
        items = v if isinstance(v, list) else [v]
        return [_config_scalar(act, x, where) for x in items]
    return _config_scalar(act, v, where)


def _config_scalar(act: argparse.Action, v, where: str):
    if isinstance(v, (dict, list)) or isinstance(v, bool):
        raise SsgwarpError(f"{where} takes {_takes(act)} (got {json.dumps(v)[:60]})")
    try:
        out = act.type(v if isinstance(v, str) else str(v)) if act.type is not None else str(v)
    except (ValueError, TypeError, OverflowError, argparse.ArgumentTypeError) as e:
        raise SsgwarpError(f"{where} takes {_takes(act)} (got {json.dumps(v)[:60]}: {_one_line(e)[:80]})") from None
    if act.choices is not None and out not in act.choices:
        raise SsgwarpError(f"{where} must be one of {', '.join(map(str, act.choices))} (got {json.dumps(v)[:60]})")
    return out


def _takes(act: argparse.Action) -> str:
    t = getattr(act.type, "__name__", None) or "a string"
    return {"int": "a whole number", "float": "a number", "Path": "a path", "str": "a string"}.get(t, t)


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    examples = "\n".join(f"  {ex}" for _, _, ex in COMMANDS.values())
    parser = argparse.ArgumentParser(
        prog="ssgwarp",
        description="Semantic-aware, structure-preserving 3D style transfer on Gaussian splats.",
        epilog=f"examples:\n{examples}\n\n'ssgwarp COMMAND --help' shows each command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", "-V", action="version", version=f"ssgwarp {version()}",
                        help="print the installed version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    subs = {}
    for name, (mod, help_, example) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_, epilog=f"example:\n  {example}",
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        p.set_defaults(_module=mod)
        subs[name] = p
    return parser, subs


def main(argv: Optional[Sequence[str]] = None) -> int:
    """The ``ssgwarp`` command. Before anything loads torch, it chooses OpenMP's passive wait policy unless the
    user set one: torch's OpenMP workers otherwise busy-wait after every parallel region and take the cores the
    CPU blending's threads need (``ssgwarp/raster/cpu_threads.py``; measured: half the CPU time of a small
    render's step, docs/notes/benchmarks-history.md). OpenMP reads it once, when torch loads, so it does nothing
    where torch was imported before (a program calling ``main``); importing ``ssgwarp`` or this module sets
    nothing."""
    if "torch" not in sys.modules:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from .services import distributed

    code = _main(argv)
    distributed.exit_after_group(code)  # (under torchrun only: see its docstring)
    return code


def _main(argv: Optional[Sequence[str]] = None) -> int:
    from .services import weights

    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("SSGWARP_DEBUG") == "1"
    if argv[:1] in (["--version"], ["-V"]):
        print(f"ssgwarp {version()}")
        return 0
    try:
        parser, subs = build_parser()
        name = next((a for a in argv if not a.startswith("-")), None)
        if name in subs:
            module = importlib.import_module(COMMANDS[name][0])
            module.add_arguments(subs[name])
            add_common(subs[name])
            _apply_config(subs[name], argv)
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            return 0
        seed_everything(args.seed)
        args.device = resolve_device(args.device)
        weights._SAID.clear()                  # each command reports a missing model once
        with weights.offline("--offline") if args.offline else contextlib.nullcontext(), weights.verbose(debug):
            return int(module.run(args) or 0)
    except SsgwarpError as e:
        if debug:
            traceback.print_exc()
        print(f"ssgwarp: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if os.environ.get("RANK", "0") == "0":  # (under torchrun: said once, by the main process)
            print("ssgwarp: interrupted; completed checkpoints are kept (rerun with --resume to continue)",
                  file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, OSError) as e:
        if debug:
            traceback.print_exc()
        print(f"ssgwarp: error: {_one_line(e)}", file=sys.stderr)
        return 2


def _one_line(e: BaseException) -> str:
    """The error as one line (libraries' multi-line texts are folded; --debug shows everything)."""
    return " ".join(str(e).split())


if __name__ == "__main__":
    sys.exit(main())
