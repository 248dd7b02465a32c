"""Stage 1 timing: seconds per key view against DDIM steps and the number of key views K.

Models:
  --arch tiny   random tiny SD-style models (default; runs anywhere in seconds)
  --arch sd15   the SD1.5 / ControlNet / CLIP ViT-L text / ViT-H image encoder architectures with
                random weights (real compute cost, no weights needed; GPU advised)
  --arch real   the real weights, found like `ssgwarp stylize` finds them (flags / env / $SSGWARP_WEIGHTS /
                the Hugging Face cache; fetch them first with `ssgwarp weights --download stage1`)

Each row runs the whole Stage 1 (VAE encode, DDIM inversion, CFG denoising with CVSA, decode) once
after a warm-up and prints total seconds, seconds per key view and peak GPU memory.
``--reconstruction`` also prints the inversion-reconstruction error (guidance 0, no CVSA) per step count.

  python benchmarks/stage1.py --device cuda --arch sd15 --size 512 --steps 10,25,50 --views 1,2,4
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))   # fakeweights: random-weight models

import torch  # noqa: E402

from ssgwarp.procedural import smooth_views  # noqa: E402
from timing import sync  # noqa: E402


def build(args, device):
    from fakeweights import random_stage1_components
    from ssgwarp.stylization.diffusion_models import Stage1Config, assemble_stage1, load_stage1

    cfg = Stage1Config(sd15=args.sd15, controlnet_depth=args.controlnet_depth, ip_adapter=args.ip_adapter,
                       image_encoder=args.image_encoder, dtype=args.dtype, progress=False)
    t = time.perf_counter()
    if args.arch == "real":
        models = load_stage1(cfg, device)
    else:
        comps = random_stage1_components(args.arch, seed=0, device=device)
        models = assemble_stage1(comps, device, cfg.torch_dtype(device))
    sync(device)
    print(f"# models: {args.arch} on {device} ({models.dtype}), built in {time.perf_counter() - t:.1f} s")
    return models, cfg


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--arch", choices=("tiny", "sd15", "real"), default="tiny")
    p.add_argument("--device", default="auto")
    p.add_argument("--dtype", default="auto", choices=("auto", "fp16", "bf16", "fp32"))
    p.add_argument("--size", type=int, default=None, help="square key views of this side (default 64 tiny, 512)")
    p.add_argument("--steps", default="5,10,20", help="comma-separated DDIM step counts")
    p.add_argument("--views", default="1,2,4", help="comma-separated K")
    p.add_argument("--guidance", type=float, default=7.5)
    p.add_argument("--no-cvsa-compare", action="store_true", help="skip the CVSA-off row at the largest K")
    p.add_argument("--views-per-call", type=int, default=None, help="CVSA query views per attention call")
    p.add_argument("--reconstruction", action="store_true", help="also print inversion-reconstruction errors")
    p.add_argument("--repeat", type=int, default=1, help="timed runs per row; the median is reported")
    p.add_argument("--json", type=Path, default=None, help="also write the rows as JSON")
    for k in ("sd15", "controlnet_depth", "ip_adapter", "image_encoder"):
        p.add_argument("--" + k.replace("_", "-"), default=None)
    args = p.parse_args(argv)

    from ssgwarp.stylization.diffusion import stylize_views

    device = torch.device("cuda" if args.device == "auto" and torch.cuda.is_available() else
                          ("cpu" if args.device == "auto" else args.device))
    size = args.size or (64 if args.arch == "tiny" else 512)
    steps_list = [int(s) for s in args.steps.split(",")]
    views_list = [int(v) for v in args.views.split(",")]
    models, base = build(args, device)
    style = torch.rand(256, 256, 3, generator=torch.Generator().manual_seed(1))

    def run(K, steps, cvsa=True):
        rgb, depth = smooth_views(K, size, size)
        cfg = base.__class__(**{**base.__dict__, "steps": steps, "guidance": args.guidance, "cvsa": cvsa,
                                "cvsa_views_per_call": args.views_per_call})
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        times = []
        for _ in range(max(1, args.repeat)):
            sync(device)
            t = time.perf_counter()
            stylize_views(models, rgb, depth, style, cfg)
            sync(device)
            times.append(time.perf_counter() - t)
        dt = sorted(times)[len(times) // 2]
        peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
        return dt, peak

    run(views_list[0], 2)  # warm-up (kernels, allocator)
    rows = []
    print(f"# Stage 1, {size}x{size} key views, guidance {args.guidance}, "
          f"CVSA views/call {args.views_per_call or 'all'}, median of {max(1, args.repeat)} run(s)")
    print(f"{'K':>3} {'steps':>6} {'cvsa':>5} {'total s':>9} {'s/view':>8} {'peak GiB':>9}")
    combos = [(K, s, True) for K in views_list for s in steps_list]
    if not args.no_cvsa_compare:
        combos += [(max(views_list), s, False) for s in steps_list]
    for K, steps, cvsa in combos:
        dt, peak = run(K, steps, cvsa)
        rows.append({"K": K, "steps": steps, "cvsa": cvsa, "seconds": dt, "seconds_per_view": dt / K,
                     "peak_gib": peak, "size": size, "arch": args.arch, "device": str(device),
                     "dtype": str(models.dtype)})
        print(f"{K:>3} {steps:>6} {('on' if cvsa else 'off'):>5} {dt:>9.3f} {dt / K:>8.3f} {peak:>9.2f}")

    if args.reconstruction:
        from diffusers import DDIMScheduler

        from ssgwarp.stylization.diffusion import ddim_denoise, ddim_invert, depth_to_control, encode_latents, schedule

        rgb, depth = smooth_views(2, size, size)
        lat = encode_latents(models, rgb)
        ctrl = depth_to_control(depth)
        text = models.encode_prompt([""]).expand(2, -1, -1)
        img = (torch.zeros(2, models.image_encoder.config.projection_dim, device=device, dtype=models.dtype)
               if models.has_ip_adapter else None)
        print("# inversion-reconstruction relative L1 error of the latents (guidance 0, no CVSA)")
        print(f"{'spacing':>9} " + " ".join(f"{s:>8}" for s in steps_list))
        for spacing in ("leading", "trailing"):
            sched = DDIMScheduler.from_config(models.scheduler.config, timestep_spacing=spacing)
            errs = []
            for s in steps_list:
                sc = schedule(sched, s)
                xt = ddim_invert(models, lat, sc, text, img, ctrl)
                x0 = ddim_denoise(models, xt, sc, text, text, img, img, ctrl, guidance=0.0)
                errs.append(float((x0 - lat).abs().mean() / lat.abs().mean()))
            print(f"{spacing:>9} " + " ".join(f"{e:>8.4f}" for e in errs))
            rows.append({"reconstruction": spacing, "steps": steps_list, "rel_l1": errs, "arch": args.arch})
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
