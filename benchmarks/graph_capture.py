"""CUDA-graph capture of the rasterizer's fixed-shape parts, measured (a route issue 16 names): host time per call.

A call has two parts around its one synchronisation (the read-back of the intersection count): before it
the projection (tile counts, packed splats) and the scan of the counts, whose shapes depend only on the
inputs; after it the binning and blending, whose shapes depend on the count. Each part that a graph can
hold is timed three ways, no gradient, in blocks of calls with one synchronisation per block (so the
host time is what is measured once it exceeds the GPU's):

- ``direct``: the launches as the rasterizer makes them;
- ``replay``: one ``torch.cuda.CUDAGraph.replay()`` of the same launches captured once, inputs already in
  the graph's buffers and outputs left there (a training step whose parameters stay where they are and
  whose outputs are consumed before the next call);
- ``replay + copies``: what a general call adds: inputs copied into the graph's buffers and outputs
  cloned out of them (every buffer of a call escapes it: into ``meta``, or into an autograd context for a
  backward that may come after further renders).

The blending's graph holds one intersection count: a training step's count changes every step, so it
would be captured again, or sized to a capacity. The whole call (``rasterization``, no gradient) is
timed for scale.

    python benchmarks/graph_capture.py                 # 16 Gaussians at 16x16 (host-bound) and 100k at 1080p
"""
from __future__ import annotations

import argparse

import torch

from raster import camera, cuda_only, make_scene
from timing import per_call_us, timed

import ssgwarp
from ssgwarp import RasterSettings
from ssgwarp.raster import blend_ops, ops


def captured(fn):
    """``(graph, outputs)``: ``fn`` run a few times on a side stream (Warp records its launches the
    first time), then captured."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = fn()
    return graph, out


def flat(out) -> list:
    if isinstance(out, torch.Tensor):
        return [out]
    return [t for o in out for t in flat(o)] if isinstance(out, (tuple, list)) else []


def case(n: int, w: int, h: int, dev) -> list[str]:
    means, quats, scales, opac, colors = make_scene(n, dev)
    vm, K = camera(w, h, dev)
    settings = RasterSettings()
    ts = 16
    tw, th = -(-w // ts), -(-h // ts)
    cfg = ops._project_cfg(torch.float32, w, h, 0.01, 1e10, 0.0, 0.3, False, settings, ts, tw, th)
    inputs = [means, quats, scales, opac, vm, K]
    sources = [t.clone() for t in inputs]

    def before():  # projection (+ tile counts, packed splats) and the scan of the counts
        scan = torch.empty(n, dtype=torch.int64, device=dev)
        side = {"ends": scan}
        m2, depths, conics, op2, _ = ops.apply(ops._Project, means, quats, scales, opac, vm, K, None, None, cfg, side)
        scan.cumsum_(0)
        return (side["radii"], m2, depths, conics, op2, side["counts"], side["splats"]), scan

    with torch.no_grad():
        (radii, m2, depths, conics, op2, counts, packed), scan = before()
        tiles = ops.bin_tiles(m2, radii, depths, ts, tw, th, counts=counts, keep_perm=False)

        def after():  # the blending forward for this intersection count (no gradient: through the ids)
            return blend_ops.blend_warp(m2, conics, colors, op2, None, tiles, w, h, ts, settings, packed=packed)

        rows = []
        for name, fn in (("before the sync: projection + scan", before), ("after it: blending forward", after)):
            graph, out = captured(fn)
            outs = flat(out)

            def replay_copies(graph=graph, outs=outs, copy_in=fn is before):
                if copy_in:  # (the blending's inputs are the projection's outputs, already in place)
                    for dst, src in zip(inputs, sources):
                        dst.copy_(src)
                graph.replay()
                return [o.clone() for o in outs]

            rows.append((name, *(per_call_us(f, dev, 500, 5) for f in (fn, graph.replay, replay_copies)), len(outs)))
        whole = per_call_us(lambda: ssgwarp.rasterization(means, quats, scales, opac, colors, vm, K, w, h),
                            dev, 500, 5)
        gpu_ms = timed(lambda: ssgwarp.rasterization(means, quats, scales, opac, colors, vm, K, w, h), dev, 20)
    lines = [f"| {n:,} | {w}x{h} | {name} | {d:.0f} | {r:.0f} | {rc:.0f} | {k} |" for name, d, r, rc, k in rows]
    lines.append(f"| {n:,} | {w}x{h} | whole call (`rasterization`, for scale; {gpu_ms:.2f} ms synchronised) | "
                 f"{whole:.0f} | - | - | - |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.parse_args()
    dev = cuda_only("graph_capture.py", "measures CUDA graphs")
    lines = ["| N | image | part | direct µs | graph replay µs | replay + inputs in / outputs out µs | outputs |",
             "|---|---|---|---|---|---|---|"]
    for n, w, h in ((16, 16, 16), (100_000, 1920, 1080)):
        for line in case(n, w, h, dev):
            lines.append(line)
            print(line, flush=True)
    print(f"\ndevice: {torch.cuda.get_device_name()}; torch {torch.__version__}\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
