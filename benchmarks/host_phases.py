"""Where a forward+backward call's time goes, phase by phase, for ssgwarp and gsplat side by side (no profiler).

Per call, synchronised before it and after it only: the forward's host time (the call until it returns; it
includes the wait for the one read-back of the intersection count, which both libraries make), the loss
(``image.sum() + alpha.sum()``), the backward's host time (``backward()`` until it returns, no wait), and
the GPU tail (from there until the device has finished). Medians over interleaved rounds (the order of the
libraries alternating), because separate runs of host-bound calls swing by up to 30 %. Where the forward's
host time differs and the tail does not, the difference is host work (Python, torch calls, launches).

    python benchmarks/host_phases.py                      # CUDA; gsplat beside ssgwarp when importable
    python benchmarks/host_phases.py --rounds 40 --no-gsplat
    python benchmarks/host_phases.py --markdown phases.md
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from raster import camera, make_scene, optional_gsplat  # noqa: E402

import ssgwarp  # noqa: E402

CASES = {"16": (16, 16, 16), "10k": (10_000, 256, 256), "100k": (100_000, 1920, 1080)}
PHASES = ("forward host", "loss", "backward host", "GPU tail", "total")


def phase_timer(raster, params, vm, K, w: int, h: int, device: torch.device):
    """A function timing one forward+backward of ``raster``: ``(forward, loss, backward, tail, total)``
    in seconds (the device synchronised before and after the call only)."""
    leaves = [p.clone().requires_grad_(True) for p in params]
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    now = time.perf_counter

    def one():
        for p in leaves:
            p.grad = None
        sync()
        t0 = now()
        img, alpha, _ = raster(*leaves, vm, K, w, h, packed=False, tile_size=16)
        t1 = now()
        loss = img.sum() + alpha.sum()
        t2 = now()
        loss.backward()
        t3 = now()
        sync()
        t4 = now()
        return t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0
    return one


def case_scene(n: int, w: int, h: int, device: torch.device):
    """``(params, viewmats, Ks)`` of a case: the benchmark scene, one camera."""
    params = make_scene(n, device)
    if n < 100:  # (a close camera so that a handful of Gaussians covers the small image)
        params[0][:, 2] -= 4.0
    return (params, *camera(w, h, device))


def interleaved(timers: dict, rounds: int, calls: int, around=None) -> dict:
    """Per library, the results of ``calls`` calls of its timer in each of ``rounds`` rounds, the order
    of the libraries alternating, after a warm-up (kernel builds, allocator pools) that is not kept.
    ``around(name)``: a context manager the library's calls run in (none when not given)."""
    ctx = around or (lambda name: contextlib.nullcontext())
    for name, t in timers.items():
        with ctx(name):
            for _ in range(max(20, calls)):
                t()
    samples: dict = {name: [] for name in timers}
    order = list(timers)
    for r in range(rounds):
        for name in (order if r % 2 == 0 else order[::-1]):
            with ctx(name):
                samples[name] += [timers[name]() for _ in range(calls)]
    return samples


def run_case(n: int, w: int, h: int, libs: dict, device: torch.device, rounds: int, calls: int) -> dict:
    params, vm, K = case_scene(n, w, h, device)
    timers = {name: phase_timer(fn, params, vm, K, w, h, device) for name, fn in libs.items()}
    samples = interleaved(timers, rounds, calls)
    return {name: [statistics.median(s[i] for s in v) * 1e6 for i in range(len(PHASES))]
            for name, v in samples.items()}


def parse(script: str, doc: str, argv, markdown_help: str):
    """``(args, device, gsplat or None)`` of the command line both host-time scripts take (cases,
    rounds, calls, device, --no-gsplat, --markdown; ``doc``: the script's docstring); exits with the
    reason on a bad one."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    ap.add_argument("--rounds", type=int, default=20, help="interleaved rounds per case")
    ap.add_argument("--calls", type=int, default=25, help="calls per library per round")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--no-gsplat", action="store_true")
    ap.add_argument("--markdown", type=Path, help=markdown_help)
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.calls < 1:
        raise SystemExit(f"{script}: --rounds and --calls must be at least 1")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"{script}: no CUDA device here (use --device cpu to time the CPU path)")
    gsplat = None if device.type == "cpu" else optional_gsplat(args.no_gsplat)
    return args, device, gsplat


def heading(device: torch.device, args) -> str:
    return (f"{datetime.date.today()}; {torch.cuda.get_device_name() if device.type == 'cuda' else 'CPU'}; "
            f"torch {torch.__version__}; medians of {args.rounds * args.calls} calls per library")


def emit(text: str, markdown: Path | None) -> None:
    """Print ``text`` and, where asked, write it to ``markdown`` (atomically)."""
    print(text)
    if markdown is not None:
        tmp = markdown.with_name(markdown.name + ".tmp")
        tmp.write_text(text + "\n")
        tmp.replace(markdown)


def main(argv=None) -> None:
    args, device, gsplat = parse("host_phases.py", __doc__, argv, "also write the table here")
    libs = {"ssgwarp": ssgwarp.rasterization}
    if gsplat is not None:
        libs["gsplat"] = gsplat.rasterization
    lines = [heading(device, args) + ", µs", "", "| case | library | " + " | ".join(PHASES) + " |",
             "|---|---|" + "---|" * len(PHASES)]
    for case in args.cases:
        n, w, h = CASES[case]
        res = run_case(n, w, h, libs, device, args.rounds, args.calls)
        for name, cols in res.items():
            lines.append(f"| {n:,} at {w}x{h} | {name} | " + " | ".join(f"{c:.0f}" for c in cols) + " |")
        if "gsplat" in res:
            ratio = [a / b for a, b in zip(res["ssgwarp"], res["gsplat"])]
            lines.append(f"| {n:,} at {w}x{h} | ssgwarp / gsplat | " + " | ".join(f"{r:.2f}" for r in ratio) + " |")
    emit("\n".join(lines), args.markdown)


if __name__ == "__main__":
    main()
