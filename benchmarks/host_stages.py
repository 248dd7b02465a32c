"""Host time of one forward+backward call, stage by stage, for ssgwarp and gsplat side by side.

`host_phases.py` splits a call into forward, loss, backward and GPU tail; this script splits the forward
and the backward further into the libraries' own stages, by wrapping each stage's function with a timer
for the run (the wrappers are removed afterwards): the projection (with its autograd op, and the op's
forward body alone), the binning (count read-back, sort, tile ranges), the blending, and what is left of
the call (argument checks, the wrapper's Python); in the backward, each autograd op's backward and the
rest (the autograd engine, the loss's sums). Per call, synchronised before and after it only; medians
over interleaved rounds. The wrappers add well under a microsecond per stage to both libraries.

    python benchmarks/host_stages.py                    # CUDA; gsplat (1.5.3's function names) beside ssgwarp
    python benchmarks/host_stages.py --cases 10k --rounds 40
    python benchmarks/host_stages.py --device cpu       # ssgwarp's CPU path alone (kernels included)
"""
from __future__ import annotations

import collections
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from host_phases import CASES, case_scene, emit, heading, interleaved, parse, phase_timer  # noqa: E402

import ssgwarp  # noqa: E402
from ssgwarp.raster import blend_ops, ops, rasterize  # noqa: E402
from ssgwarp.raster import launch as L  # noqa: E402

now = time.perf_counter
SPENT: dict = collections.defaultdict(float)  # stage -> seconds in the current call

# (stage, label per library); the forward's stages first, then the backward's
ROWS = [
    ("argument checks", "check_shapes", None),
    ("projection (+ SH), with its autograd op", "projection", "projection"),
    ("  of which the op's forward body", "projection body", "projection body"),
    ("binning: read-back, sort, tile ranges", "binning", "binning"),
    ("  of which the wait for the count", "wait", None),
    ("  of which the sort", "sort", None),
    ("blending, with its autograd op", "blending", "blending"),
    ("  of which the op's forward body", "blending body", "blending body"),
    ("rest of the forward (the call's own Python)", "forward rest", "forward rest"),
    ("forward host total", "forward", "forward"),
    ("loss (image.sum() + alpha.sum())", "loss", "loss"),
    ("backward: projection op", "B projection", "B projection"),
    ("backward: blending op", "B blending", "B blending"),
    ("backward: rest (autograd engine, the sums)", "backward rest", "backward rest"),
    ("backward host total", "backward", "backward"),
    ("GPU tail", "tail", "tail"),
    ("total", "total", "total"),
]
FORWARD_PARTS = ("check_shapes", "projection", "binning", "blending")
BACKWARD_PARTS = ("B projection", "B blending")


class Wrapped:
    """Timers around named attributes (functions, or an autograd Function's static methods) for the
    ``with`` block: each call adds its time to ``SPENT[label]``."""

    def __init__(self, spec):
        self.spec = spec  # (owner, attribute name, label, static method?)
        self.saved = []

    def __enter__(self):
        for owner, name, label, static in self.spec:
            f = getattr(owner, name, None)
            if f is None:  # (another gsplat version: that stage stays in the rest)
                continue

            def timed(*a, _f=f, _label=label, **k):
                t = now()
                try:
                    return _f(*a, **k)
                finally:
                    SPENT[_label] += now() - t
            self.saved.append((owner, name, owner.__dict__[name]))
            setattr(owner, name, staticmethod(timed) if static else timed)
        return self

    def __exit__(self, *exc):
        for owner, name, orig in reversed(self.saved):
            setattr(owner, name, orig)


def ssgwarp_stages():
    return [(rasterize, "check_shapes", "check_shapes", False), (ops, "apply", "projection", False),
            (ops._Project, "forward", "projection body", True), (ops, "bin_tiles", "binning", False),
            (L, "finish_read_int64", "wait", False), (L, "sort_pairs", "sort", False),
            (blend_ops, "blend_warp", "blending", False), (blend_ops._Blend, "forward", "blending body", True),
            (ops._Project, "backward", "B projection", True), (blend_ops._Blend, "backward", "B blending", True)]


def gsplat_stages(gsplat):
    import gsplat.cuda._wrapper as gw
    import gsplat.rendering as gr
    return [(gr, "fully_fused_projection", "projection", False), (gr, "spherical_harmonics", "projection", False),
            (gw._FullyFusedProjection, "forward", "projection body", True), (gr, "isect_tiles", "binning", False),
            (gr, "isect_offset_encode", "binning", False), (gr, "rasterize_to_pixels", "blending", False),
            (gw._RasterizeToPixels, "forward", "blending body", True),
            (gw._FullyFusedProjection, "backward", "B projection", True),
            (gw._RasterizeToPixels, "backward", "B blending", True)]


def stage_timer(raster, params, vm, K, w: int, h: int, device: torch.device):
    """One forward+backward of ``raster`` (:func:`host_phases.phase_timer`): a dict of seconds per label
    of :data:`ROWS`."""
    phases = phase_timer(raster, params, vm, K, w, h, device)

    def one():
        SPENT.clear()
        d = dict(zip(("forward", "loss", "backward", "tail", "total"), phases()))
        d.update(SPENT)
        d["forward rest"] = d["forward"] - sum(d.get(k, 0.0) for k in FORWARD_PARTS)
        d["backward rest"] = d["backward"] - sum(d.get(k, 0.0) for k in BACKWARD_PARTS)
        return d
    return one


def run_case(n: int, w: int, h: int, libs: dict, device: torch.device, rounds: int, calls: int) -> dict:
    params, vm, K = case_scene(n, w, h, device)
    timers = {name: stage_timer(fn, params, vm, K, w, h, device) for name, (fn, _) in libs.items()}
    samples = interleaved(timers, rounds, calls, around=lambda name: Wrapped(libs[name][1]))
    return {name: {k: statistics.median(d.get(k, 0.0) for d in v) * 1e6 for k in {k for d in v for k in d}}
            for name, v in samples.items()}


def table(n, w, h, res: dict) -> list:
    names = list(res)
    both = len(names) == 2
    head = names + (["ssgwarp / gsplat"] if both else [])
    lines = [f"\n{n:,} Gaussians at {w}x{h}, µs", "", "| stage | " + " | ".join(head) + " |",
             "|---|" + "---|" * len(head)]
    for stage, *labels in ROWS:
        got = [res[name].get(lab) if lab else None for name, lab in zip(names, labels)]
        cells = ["-" if v is None else f"{v:.0f}" for v in got]
        if both:
            cells.append(f"{got[0] / got[1]:.2f}" if None not in got and got[1] > 0 else "-")
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None) -> None:
    args, device, gsplat = parse("host_stages.py", __doc__, argv, "also write the tables here")
    libs = {"ssgwarp": (ssgwarp.rasterization, ssgwarp_stages())}
    if gsplat is not None:
        libs["gsplat"] = (gsplat.rasterization, gsplat_stages(gsplat))
    lines = [heading(device, args)]
    for case in args.cases:
        n, w, h = CASES[case]
        lines += table(n, w, h, run_case(n, w, h, libs, device, args.rounds, args.calls))
    emit("\n".join(lines), args.markdown)


if __name__ == "__main__":
    main()
