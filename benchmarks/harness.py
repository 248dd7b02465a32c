"""The benchmark tools' shared harness: data location, machine name, timing (warm-up, repeats, median / min / max),
modes, JSON lines, markdown tables and figures. ``python benchmarks/<tool>.py`` puts this folder on ``sys.path``."""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
# beside the repository (the development machines), the GPU machine's copy, a checkout inside the
# repository, the shared copy of a worktree
CANDIDATES = (ROOT.parent / "shared" / "data", Path("/root/data"), ROOT / "shared" / "data", Path("/work/shared/data"))
STYLE_SUFFIXES = (".jpg", ".jpeg", ".png")


def dispatch(modes: dict, default, argv=None) -> int:
    """``modes[argv[0]](argv[1:])`` when the first argument names a mode, else ``default(argv)``; an ``InputError``
    (any ``SsgwarpError``) either raises: one line naming the tool and mode, exit status 2."""
    from ssgwarp.errors import SsgwarpError

    argv = sys.argv[1:] if argv is None else list(argv)
    mode = argv[0] if argv and argv[0] in modes else ""
    fn = modes[mode] if mode else default
    try:
        return fn(argv[1:] if mode else argv)
    except SsgwarpError as e:
        print(f"{Path(fn.__code__.co_filename).name}{' ' + mode if mode else ''}: {e}", file=sys.stderr)
        return 2


def parser(prog: str, doc: str) -> argparse.ArgumentParser:
    """An argument parser whose ``--help`` shows ``doc`` as written (its examples' line breaks kept)."""
    return argparse.ArgumentParser(prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)


def knobs(pairs, *targets) -> list[dict]:
    """``KEY=VALUE`` strings as one dict per target (dataclass instances): a key goes to the first target with that
    field, its value typed as the field's value there (None: a number); an unknown key raises ``InputError``."""
    from ssgwarp.errors import InputError

    out = [{} for _ in targets]
    for k, _, v in (p.strip().partition("=") for p in pairs if p.strip()):
        k, v = k.strip().replace("-", "_"), v.strip()
        i = next((i for i, t in enumerate(targets) if hasattr(t, k)), None)
        if i is None:
            raise InputError(f"{k}={v}: no such field of {' or '.join(type(t).__name__ for t in targets)}")
        like = getattr(targets[i], k)
        kind = type(like) if isinstance(like, (str, float)) else int if v.lstrip("-").isdigit() else float
        try:
            out[i][k] = v.lower() in ("1", "true", "yes", "on") if isinstance(like, bool) else kind(v)
        except ValueError:
            raise InputError(f"{k}={v}: {type(targets[i]).__name__}.{k} takes a number") from None
    return out


def data_root() -> Path:
    """The first candidate folder that exists (the first one when none does, for the error message)."""
    return next((p for p in CANDIDATES if p.is_dir()), CANDIDATES[0])


# the shared captures by short name: (folder under the data root, image sub-folder)
CAPTURES = {"fern8": ("llff_fern", "images_8"), "fern4": ("llff_fern", "images_4"), "cup": ("colmap_cup", "images"),
            "lego": ("lego_200", "images"), "livingroom": ("livingroom_360", "images"),
            "bird": ("bird_360", "images")}


def capture_folder(spec: str, root: Path | None = None) -> tuple[Path, str]:
    """``(folder, image sub-folder)`` of a capture named by ``spec``: a name of :data:`CAPTURES` (under ``root``,
    default :func:`data_root`) or ``PATH[:IMAGES]`` (default ``images``); raises ``InputError`` when the folder
    is missing."""
    from ssgwarp.errors import InputError

    if spec in CAPTURES:
        name, images = CAPTURES[spec]
        folder = Path(root or data_root()) / name
    else:
        path, _, images = spec.partition(":")
        folder, images = Path(path).expanduser(), images or "images"
    if not folder.is_dir():
        raise InputError(f"capture {spec!r}: {folder} is not a folder (shared captures: {', '.join(CAPTURES)}; "
                         "or give PATH[:IMAGES], or --data-root)")
    return folder, images


def style_paths(spec: str, folder: Path) -> list[Path]:
    """The style images named by ``spec`` (comma-separated names without extension, or paths; empty: every
    image in ``folder``, sorted by name); raises ``InputError`` naming what was not found."""
    from ssgwarp.errors import InputError

    folder = Path(folder)
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in STYLE_SUFFIXES) if folder.is_dir() else []
    if not spec:
        if not images:
            raise InputError(f"no style images in {folder}: give the styles or their folder")
        return images
    out = []
    for name in (n.strip() for n in spec.split(",") if n.strip()):
        p = Path(name)
        found = p if p.is_file() else next((q for q in images if q.stem == name), None)
        if found is None:
            raise InputError(f"style {name!r}: not a file and not an image in {folder}")
        out.append(found)
    return out


# ----------------------------------------------------------------------------- the machine
def machine(device: torch.device | str = "cpu") -> str:
    """The GPU's name, or the CPU's model, cores and torch's thread count."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    cpu = platform.processor() or platform.machine()
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}"


def header(device: torch.device | str = "cpu", what: str = "") -> str:
    """One line for the top of a table: the date, the machine, torch and warp versions, ``what``."""
    import warp

    return f"{datetime.date.today().isoformat()}, {machine(device)}, torch {torch.__version__}, warp " \
        f"{warp.__version__}" + (f"; {what}" if what else "")


# ----------------------------------------------------------------------------- timing
def sync(device: torch.device | str) -> None:
    """Wait for the device's queued work (CUDA); nothing on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def stats(ms: list[float]) -> dict:
    """``{median, min, max, n}`` of a list of milliseconds."""
    return {"median": statistics.median(ms), "min": min(ms), "max": max(ms), "n": len(ms)}


def measure(fn, device, repeats: int = 10, warmup: int = 1, clock=time.perf_counter) -> dict:
    """Milliseconds of ``repeats`` synchronised calls of ``fn()`` after ``warmup`` calls (kernel compilation,
    JIT, clocks): ``{median, min, max, n}``. ``clock``: ``time.process_time`` suits a shared CPU."""
    return interleaved({0: fn}, device, repeats, rounds=1, warmup=warmup, clock=clock)[0]


def interleaved(fns: dict, device, repeats: int, rounds: int = 4, warmup: int = 1, clock=time.perf_counter) -> dict:
    """:func:`stats` of each function, timed in turns (``rounds`` rounds of ``repeats / rounds`` synchronised
    calls each), so that a drifting GPU clock or host load affects all of them alike."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    sync(device)
    out = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            for _ in range(max(1, repeats // rounds)):
                t0 = clock()
                fn()
                sync(device)
                out[k].append((clock() - t0) * 1e3)
    return {k: stats(v) for k, v in out.items()}


def passes(raster, params: list, args: tuple, weight=None, **kw):
    """``(fwd, fwd_bwd, leaves)``: a call of ``raster(*params, *args, **kw)`` without gradients, and one with the
    backward of ``(image * weight).sum() + alpha.sum()`` into ``leaves`` (copies of ``params``, made once)."""
    leaves = [p.detach().clone().requires_grad_(True) for p in params]

    def fwd():
        with torch.no_grad():
            return raster(*params, *args, **kw)

    def fwd_bwd():
        for p in leaves:
            p.grad = None
        img, alpha, _ = raster(*leaves, *args, **kw)
        ((img if weight is None else img * weight).sum() + alpha.sum()).backward()
    return fwd, fwd_bwd, leaves


def per_call_us(fn, device, calls: int, blocks: int, clock=time.perf_counter) -> float:
    """Microseconds per call of the fastest of ``blocks`` blocks of ``calls`` calls, one synchronisation per
    block (queued GPU work overlaps the host, as in a training loop), after ``max(20, calls // 10)`` warm-up
    calls."""
    for _ in range(max(20, calls // 10)):
        fn()
    sync(device)
    best = float("inf")
    for _ in range(blocks):
        t0 = clock()
        for _ in range(calls):
            fn()
        sync(device)
        best = min(best, (clock() - t0) / calls * 1e6)
    return best


def cuda_kernel_ms(fn, calls: int = 5) -> dict:
    """GPU milliseconds per call of each CUDA kernel ``fn`` launches (torch profiler, after three warm-up
    calls), by kernel name."""
    from torch.profiler import ProfilerActivity, profile

    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as p:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()
    per: dict = {}
    for e in p.events():
        if e.device_type.name == "CUDA":
            per[e.name] = per.get(e.name, 0.0) + e.device_time / calls / 1e3
    return per


def warm_gpu(seconds: float = 1.0) -> None:
    """Busy the GPU for a moment so its clocks are up before the first timing."""
    x = torch.randn(4096, 4096, device="cuda")
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        x = (x @ x).clamp_(-1, 1)
    torch.cuda.synchronize()


def optional_gsplat(skip: bool = False):
    """The gsplat module, or None (asked to skip it, or not importable: then said so once)."""
    if skip:
        return None
    try:
        import gsplat
    except Exception as e:  # noqa: BLE001
        print(f"gsplat not available ({e}); its columns stay empty")
        return None
    return gsplat


# ----------------------------------------------------------------------------- output
def append_jsonl(path: Path | str | None, row: dict) -> None:
    """Append ``row`` as one JSON line to ``path`` (nothing when ``path`` is None)."""
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(row, default=str) + "\n")


def fmt(v, digits: int = 2) -> str:
    """A table cell: '-' for None / NaN, thousands separators for integers, small floats in e-notation."""
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return str(v)
    if isinstance(v, int):
        return f"{v:,}"
    return f"{v:.2e}" if v != 0 and abs(v) < 1e-2 else f"{v:.{digits}f}"


def table(rows: list[dict], cols) -> str:
    """A markdown table of ``rows``: ``cols`` is a list of ``(key, title)`` or ``(key, title, digits)`` (columns no
    row has are left out)."""
    cols = [(*c, 2)[:3] for c in cols if any(c[0] in r for r in rows)]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(k), d) for k, _, d in cols) + " |" for r in rows]
    return "\n".join(lines)


def write_text(path: Path | str, text: str) -> None:
    """Write ``text`` to ``path`` atomically (the folder made)."""
    from ssgwarp.core.fileio import atomic_path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path: Path | str, **savefig) -> Path:
    """Write a matplotlib figure atomically (``savefig``'s keywords: format, dpi, ...) and close it."""
    from ssgwarp.core.fileio import atomic_path

    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, **savefig)
    pyplot().close(fig)
    return Path(path)
