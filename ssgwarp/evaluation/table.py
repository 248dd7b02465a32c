"""The markdown table ``ssgwarp evaluate`` prints and writes: one column per run, one row per
metric (consistency, style, content, quality), and where it goes by default."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

PAIR_KINDS = ("short", "long")


# ----------------------------------------------------------------------------- the table
def _fmt(x: Any, digits: int = 4) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}g}" if abs(x) < 1e4 else f"{x:.3e}"
    return str(x)


def _run_labels(results: Sequence[dict]) -> list[str]:
    labels = [Path(r["run"]).name for r in results]
    if len(set(labels)) < len(labels):
        labels = ["/".join(Path(r["run"]).parts[-2:]) for r in results]
    return labels


def comparison_table(results: Sequence[dict], notes: bool = True) -> str:
    """One markdown table, one column per run, one row per metric (lower is better unless marked ↑);
    ``notes``: with the list of what was skipped and why (the console has said it already)."""
    labels = _run_labels(results)
    rows: list[tuple[str, list[str]]] = []

    def row(name: str, fn) -> None:
        vals = []
        for r in results:
            try:
                vals.append(fn(r))
            except (KeyError, TypeError, IndexError):
                vals.append("-")
        if any(v != "-" for v in vals):
            rows.append((name, vals))

    row("kind", lambda r: r["kind"] + (f" ({r['mode']})" if r.get("mode") else ""))
    row("views, resolution", lambda r: f"{r['views']} ({r['view_split']}), {r['resolution'][0]}x{r['resolution'][1]}")
    row("views scored", lambda r: r["views_scored"])
    warps = sorted({w for r in results for w in r.get("consistency", {})}, key=lambda w: w != "reprojection")
    for w in warps:
        for kind in PAIR_KINDS:
            def get(r, w=w, kind=kind, key="rmse"):
                return r["consistency"][w][kind][key]
            label = f"{kind}-range"
            row(f"{label} RMSE ({w})", lambda r, g=get: _fmt(g(r)) + (f" (gap {g(r, key='gap')}, "
                                                                        f"{g(r, key='pairs')} pairs, "
                                                                        f"{_fmt(100 * g(r, key='coverage'), 3)}% px)"
                                                                        if g(r, key='coverage') is not None else ""))
            row(f"{label} LPIPS ({w})", lambda r, g=get: _fmt(g(r, key="lpips")))
    row("colour distance (SW, Lab)", lambda r: _fmt(r["style_content"]["style_distance_color"]) + (
        f" (source {_fmt(r['style_content']['style_distance_color_original'])})"
        if "style_distance_color_original" in r["style_content"] else ""))
    row("texture distance (SW, filters)", lambda r: _fmt(r["style_content"]["style_distance_texture"]) + (
        f" (source {_fmt(r['style_content']['style_distance_texture_original'])})"
        if "style_distance_texture_original" in r["style_content"] else ""))
    row("Gram style loss", lambda r: _fmt(r["style_content"]["gram_style_loss"]))
    row("content loss", lambda r: _fmt(r["style_content"]["content_loss"]))
    row("feature extractor", lambda r: r["style_content"]["extractor"])
    row("PSNR dB ↑", lambda r: f"{r['quality']['psnr']:.2f} ({r['quality']['split']})")
    row("SSIM ↑", lambda r: f"{r['quality']['ssim']:.4f}")
    row("LPIPS (quality)", lambda r: _fmt(r["quality"]["lpips"]))
    row("Gaussians", lambda r: str(r["gaussians"]))
    row("time s", lambda r: f"{r['time_s']:.1f}")

    head = "| metric | " + " | ".join(labels) + " |"
    sep = "|---|" + "---|" * len(labels)
    body = ["| " + name + " | " + " | ".join(vals) + " |" for name, vals in rows]
    notes_ = []
    which: dict[tuple[str, str], list[str]] = {}
    for label, r in zip(labels, results if notes else ()):
        for k, v in (r.get("skipped") or {}).items():
            which.setdefault((k, v), []).append(label)
    for (k, v), who in which.items():
        scope = "" if len(who) == len(results) else f" ({', '.join(who)})"
        notes_.append(f"- {k} skipped{scope}: {v}")
    date = results[0].get("date", "") if results else ""
    dev = results[0].get("device", "") if results else ""
    title = f"Evaluation ({date}, {dev}). Lower is better except ↑. RMSE on [0,1] colours over co-visible pixels."
    return "\n".join([title, "", head, sep, *body, *([""] + notes_ if notes_ else [])]) + "\n"


def default_table_path(runs: Sequence[Path]) -> Path:
    import os

    if len(runs) == 1:
        return runs[0] / "evaluation" / "table.md"
    common = Path(os.path.commonpath([str(p.resolve()) for p in runs]))
    return common / "evaluation.md"
