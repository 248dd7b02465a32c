"""Make the demo's figure and numbers in the README and docs/demo.md from one real demo run.

    python docs/make_figures.py                 # runs `ssgwarp demo` (default size, CPU) in a temporary folder
    python docs/make_figures.py --keep DIR      # the same, into DIR (kept)
    python docs/make_figures.py --run DIR       # or reads a finished demo run (its summary.json)

Writes docs/images/demo_contact_sheet.png (the run's contact sheet) and rewrites the text between the
markers ``<!-- figures:demo -->`` ... ``<!-- /figures -->`` (the demo's groups, purity, style distances and
time) in README.md and docs/demo.md, and ``<!-- figures:demo-table -->`` ... ``<!-- /figures -->`` (the
stage times) in docs/demo.md. Nothing else in those files is touched. tests/test_demo.py holds a fresh demo
run to the numbers written here (within ``ssgwarp.demo.CLAIM_TOLERANCE``).
"""
from __future__ import annotations

import argparse
import datetime
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

from ssgwarp.core.fileio import atomic_path, read_json  # noqa: E402
from ssgwarp.demo import claims_text, run_demo  # noqa: E402

SHEET = ROOT / "docs" / "images" / "demo_contact_sheet.png"
CLAIM_FILES = (ROOT / "README.md", ROOT / "docs" / "demo.md")
TABLE_FILE = ROOT / "docs" / "demo.md"
END = "<!-- /figures -->"
# the default demo on a 2-core CPU machine with nothing else running (runs of `/usr/bin/time ssgwarp demo`)
IDLE_RANGE = ("about 35 s (measured 2026-12-07 on a shared 2-core host: 34-42 s with the start of Python, 31-38 s "
              "by its own clock; 26-29 s on the faster machine of 2026-11-28)")


def span(text: str, name: str, body: str, where: Path) -> str:
    """``text`` with the part between ``<!-- figures:NAME -->`` and the next ``<!-- /figures -->`` replaced."""
    start = f"<!-- figures:{name} -->"
    pat = re.compile(re.escape(start) + r".*?" + re.escape(END), re.S)
    if not pat.search(text):
        raise SystemExit(f"make_figures: {where} has no {start} ... {END} span; add the markers where the "
                         f"numbers belong")
    return pat.sub(lambda _: f"{start}{body}{END}", text)


def time_text(s: dict, load: float | None, when: str) -> str:
    cores = os.cpu_count() or 0
    where = f"a {cores}-core {s['device'].upper()} machine"
    if load is not None and load > 0.5 * max(cores, 1):
        # a busy machine's time says little about the demo: it is given with the load, next to the idle range
        return (f"This run took {s['total_seconds']:.0f} s on {where} shared with other work (load average "
                f"{load:.1f}; {when}); on an idle {cores}-core machine the demo takes {IDLE_RANGE}")
    if load is None:                                          # a run read back: its machine's load is unknown
        return (f"This run took {s['total_seconds']:.0f} s on {where} ({when}); on an idle {cores}-core machine "
                f"the demo takes {IDLE_RANGE}")
    return f"The whole demo took {s['total_seconds']:.0f} s on {where} ({when})"


def stage_table(s: dict, when: str) -> str:
    sec, sub = s["seconds"], s.get("stylize_substages") or {}
    rows = [("procedural data", sec.get("data")),
            (f"reconstruct ({s['gaussians']} Gaussians, held-out PSNR {s['psnr']:.2f} dB)", sec.get("reconstruct")),
            (f"group ({s['group_kind']}, K = {s['groups']}, purity {s['group_purity']:.3f}, "
             f"{s['objects_separated']}/{len(s['objects'])} objects separated)", sec.get("group")),
            (f"stylize (Stage 2 {sub.get('stage2', 0):.1f} s; Stage 1 "
             f"{'ran' if s['stage1'].get('ran') else 'skipped: no weights'})", sec.get("stylize")),
            ("evaluate (both runs)", sec.get("evaluate")), ("contact sheet", sec.get("sheet"))]
    lines = ["", "", f"`ssgwarp demo --device {s['device']}` ({s['size']} size, seed {s['seed']}; {when}):", "",
             "| stage | seconds |", "|---|---|"]
    lines += [f"| {what} | {v:.1f} |" for what, v in rows if v is not None]
    lines += [f"| **total** | **{s['total_seconds']:.1f}** |", "", ""]
    return "\n".join(lines)


def write(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, help="a finished demo run to read instead of running the demo")
    ap.add_argument("--device", default="cpu", help="device of the demo run (default cpu, as the README states)")
    ap.add_argument("--keep", type=Path, help="run the demo into this folder and keep it (default: a temporary one)")
    args = ap.parse_args(argv)
    for f in CLAIM_FILES:                       # the markers first: no demo run for a file that cannot take it
        span(f.read_text(), "demo", "", f)
    span(TABLE_FILE.read_text(), "demo-table", "", TABLE_FILE)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    if args.run is not None:
        summary = read_json(args.run / "summary.json")
        when = datetime.datetime.fromtimestamp((args.run / "summary.json").stat().st_mtime).strftime("%Y-%m-%d")
        load = None
        tmp = None
    else:
        tmp = None if args.keep else Path(tempfile.mkdtemp(prefix="ssgwarp-figures-"))
        t0 = time.perf_counter()
        summary = run_demo(args.keep or tmp / "demo", "default", device=args.device, progress=False)
        when = datetime.date.today().isoformat()
        print(f"make_figures: demo ran in {time.perf_counter() - t0:.1f} s", flush=True)
    try:
        SHEET.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(SHEET) as t:
            shutil.copyfile(summary["contact_sheet"], t)
        claim = claims_text(summary) + ". " + time_text(summary, load, when) + "."
        for f in CLAIM_FILES:
            write(f, span(f.read_text(), "demo", claim, f))
        write(TABLE_FILE, span(TABLE_FILE.read_text(), "demo-table", stage_table(summary, when), TABLE_FILE))
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    print(f"make_figures: {claim}\nmake_figures: wrote {SHEET.relative_to(ROOT)}, "
          f"{', '.join(str(f.relative_to(ROOT)) for f in CLAIM_FILES)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
