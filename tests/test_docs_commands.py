"""The README's commands, as a new user types them, on the shared real data at a tiny size (issue 60: docs that
match behaviour). The `--quick` table's three commands are read from README.md itself (data/fern -> the shared
fern, candy.jpg -> the shared style, runs/ -> a temporary folder) with tiny sizes appended (options given
explicitly win over `--quick`); then the pipeline table's key views, render, export and evaluate on their
outputs. Skips when the shared data is absent (a user's clone)."""
from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from conftest import SHARED_DATA
from ssgwarp.cli import main

ROOT = Path(__file__).resolve().parents[1]
FERN, CANDY = SHARED_DATA / "llff_fern", SHARED_DATA / "styles" / "candy.jpg"
TINY = {"reconstruct": ["--iters", "10", "--width", "32", "--max-gaussians", "2000"],
        "group": ["--iters", "3"],
        "stylize": ["--iters", "2", "--path-frames", "2", "--max-side", "32"]}


def readme_quick_commands() -> list[str]:
    """The first column of the README's `--quick` table: ``ssgwarp ...`` commands in backticks."""
    text = (ROOT / "README.md").read_text()
    return re.findall(r"^\| `(ssgwarp (?:reconstruct|group|stylize) [^`]*--quick)` \|", text, flags=re.M)


def test_the_readme_lists_the_quick_commands():
    cmds = readme_quick_commands()
    assert [c.split()[1] for c in cmds] == ["reconstruct", "group", "stylize"], cmds


@pytest.mark.slow     # (about 20 s of CPU: five commands on the real fern at 32 px)
@pytest.mark.skipif(not (FERN / "images_8").is_dir() or not CANDY.is_file(), reason="needs ../shared/data")
def test_readme_commands_run_on_the_shared_data(tmp_path, capsys):
    runs = tmp_path / "runs"

    def argv(cmd: str) -> list[str]:
        words = shlex.split(cmd)[1:]
        out = []
        for w in words:
            w = w.replace("data/fern", str(FERN)).replace("candy.jpg", str(CANDY))
            out.append(str(runs / w[len("runs/"):]) if w.startswith("runs/") else w)
        return out + TINY[words[0]] + ["--device", "cpu"]

    for cmd in readme_quick_commands():
        assert main(argv(cmd)) == 0, cmd
    fern, styled = runs / "fern", runs / "fern-candy"
    m = json.loads((fern / "metrics.json").read_text())
    assert m["resolution"] == [32, 24] and m["iters"] == 10
    assert json.loads((fern / "groups" / "groups.json").read_text())["K"] >= 1
    assert (styled / "scene.ply").is_file() and (styled / "path.gif").is_file()
    # the pipeline table's other commands on these runs
    assert main(["keyviews", str(fern), "--max-side", "32", "--device", "cpu"]) == 0
    assert main(["render", str(styled), "--out", str(tmp_path / "frames"), "--path", "2", "--no-progress",
                 "--device", "cpu"]) == 0
    assert main(["export", str(styled), "--out", str(tmp_path / "fern.spz"), "--check-views", "1"]) == 0
    assert main(["evaluate", str(styled), "--device", "cpu", "--path-frames", "3", "--max-side", "32",
                 "--quiet"]) == 0
