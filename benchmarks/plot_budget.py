"""Plot quality against size from ``benchmarks/reconstruct.py`` results: the MCMC budget sweep beside the
other strategies of the same scene.

Reads one or more ``results.json`` files (their ``rows``), keeps the rows of ``--scene`` at ``--iters``, and
draws held-out PSNR against the final Gaussian count and against peak GPU memory: one line for the MCMC
budget sweep (each point labelled with its budget and train time), one marker per other run (strategy,
backend, D-SSIM scale). Writes a PNG (default ``docs/tradeoffs_budget.png``).

    python benchmarks/plot_budget.py sweep/results.json f8ours/results.json f8gs/results.json \\
        dssim/results.json --scene fern8 --iters 7000 --out docs/tradeoffs_budget.png
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_rows(paths: list[Path], scene: str, iters: int) -> list[dict]:
    """The rows of ``scene`` at ``iters`` from every file, in file order."""
    rows = []
    for p in paths:
        data = json.loads(Path(p).read_text())
        rows += [r for r in data.get("rows", []) if r.get("scene") == scene and r.get("iters") == iters]
    if not rows:
        raise SystemExit(f"no rows of scene {scene!r} at {iters} steps in {', '.join(map(str, paths))}")
    return rows


def label(r: dict) -> str:
    """A legend entry for a run that is not part of the budget sweep."""
    parts = [r["strategy"]]
    if r.get("matched"):
        parts.append(f"budget = default's count ({r['max_gaussians']:,})")
    if r.get("backend", "ssgwarp") != "ssgwarp":
        parts.append(f"{r['backend']} rasterizer")
    if r.get("dssim_scale", 1.0) != 1.0:
        parts.append(f"D-SSIM x{r['dssim_scale']:g}")
    return ", ".join(parts)


def _by_point(rows: list[dict], key: str) -> dict:
    """Rows that ended alike (same Gaussian count, PSNR to 0.1 dB) grouped under their first row's point."""
    out: dict = {}
    for r in rows:
        out.setdefault((r["gaussians"], round(r["psnr"], 1)), []).append(r)
    return {(same[0][key], same[0]["psnr"]): same for same in out.values()}


def plot(rows: list[dict], out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sweep = sorted((r for r in rows if r["strategy"] == "mcmc" and not r.get("matched")),
                   key=lambda r: r["max_gaussians"])
    others = [r for r in rows if r not in sweep]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.4))
    cmap = plt.get_cmap("tab10")
    for ax, key, xlabel in ((axes[0], "gaussians", "Gaussians at the end"),
                            (axes[1], "peak_mib", "peak GPU memory (MiB)")):
        if sweep:
            ax.plot([r[key] for r in sweep], [r["psnr"] for r in sweep], "o-", color="k", label="mcmc, budget sweep",
                    zorder=3)
            for pt, same in _by_point(sweep, key).items():  # budgets that ended at one count share a label
                text = " / ".join(f"{r['max_gaussians'] // 1000}k" for r in same) + " budget, " + \
                    " / ".join(f"{r['seconds']:.0f}" for r in same) + " s"
                ax.annotate(text, pt, fontsize=7, xytext=(4, -10), textcoords="offset points")
        for j, r in enumerate(others):
            ax.scatter([r[key]], [r["psnr"]], color=cmap(j % 10), marker="s", s=40, label=label(r), zorder=3)
            ax.annotate(f"{r['seconds']:.0f} s", (r[key], r["psnr"]), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("held-out PSNR (dB)")
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=4, frameon=False)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    from ssgwarp.core.fileio import atomic_path

    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", nargs="+", type=Path, help="results.json files of benchmarks/reconstruct.py")
    ap.add_argument("--scene", default="fern8")
    ap.add_argument("--iters", type=int, default=7000)
    ap.add_argument("--title", default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "tradeoffs_budget.png")
    a = ap.parse_args(argv)
    rows = load_rows(a.results, a.scene, a.iters)
    title = a.title or f"{a.scene}, {a.iters} steps: held-out PSNR against size (times in the labels)"
    print(plot(rows, a.out, title))
    return 0


if __name__ == "__main__":
    sys.exit(main())
