"""Stylize's render/write phase, taken apart: rendering the views, encoding and writing their PNGs, and the
path video, one after the other (as ``stylize`` did before issue 63) and with the encoding and writing on
background threads (:class:`ssgwarp.core.fileio.ImageWriter`, what ``stylize`` does now).

The scene is the demo's procedural one (no data needed); ``--width`` sets the views' size (4:3). Prints one
markdown table: wall seconds (and the process's CPU seconds) of each part and of both ways.

    python benchmarks/writes.py --views 77 --width 320 --device cpu
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _clock():
    return time.perf_counter(), time.process_time()


def _since(t):
    return time.perf_counter() - t[0], time.process_time() - t[1]


def main(argv=None) -> int:
    from ssgwarp import procedural as P
    from ssgwarp.core.fileio import ImageWriter, write_image
    from ssgwarp.core.imaging import write_video
    from ssgwarp.stylization.stage2 import render_rgb

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=77, help="images written (stylize at fern images_4: 17 + 60)")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--density", type=float, default=1.0, help="the procedural scene's density")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    dev = torch.device(a.device)
    scene = P.build_scene(a.density, seed=0).scene.to(dev)
    cams = P.ring_cameras(a.views, a.width, a.width * 3 // 4).to(dev)
    bg = torch.tensor(P.BACKGROUND, dtype=torch.float32, device=dev)

    def render(i):
        with torch.no_grad():
            img = render_rgb(scene, cams[[i]], bg)[0].clamp(0, 1)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        return img

    render(0)  # (kernels loaded, caches warm)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        t = _clock()
        imgs = [render(i) for i in range(a.views)]
        rows.append(("render", *_since(t)))
        t = _clock()
        for i, img in enumerate(imgs):
            write_image(out / "a" / f"frame_{i:04d}.png", img)
        rows.append(("PNG encode + write", *_since(t)))
        frames = [(img.float().cpu().numpy() * 255 + 0.5).astype(np.uint8) for img in imgs]
        t = _clock()
        write_video(out / "a.gif", frames)
        rows.append(("path video (GIF)", *_since(t)))
        t = _clock()
        frames = []
        for i in range(a.views):
            img = render(i)
            write_image(out / "b" / f"frame_{i:04d}.png", img)
            frames.append((img.float().cpu().numpy() * 255 + 0.5).astype(np.uint8))
        write_video(out / "b.gif", frames)
        rows.append(("all, one after the other (before)", *_since(t)))
        t = _clock()
        frames = []
        with ImageWriter() as w:
            for i in range(a.views):
                img = render(i)
                w.image(out / "c" / f"frame_{i:04d}.png", img)
                frames.append((img.float().cpu().numpy() * 255 + 0.5).astype(np.uint8))
            w.call(write_video, out / "c.gif", frames)
        rows.append(("all, writes on background threads (now)", *_since(t)))
    h = a.width * 3 // 4
    print(f"{a.views} views {a.width}x{h}, {len(scene)} Gaussians, device {dev}, torch threads "
          f"{torch.get_num_threads()}")
    print("| part | wall s | CPU s |\n|---|---:|---:|")
    for name, w, c in rows:
        print(f"| {name} | {w:.2f} | {c:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
