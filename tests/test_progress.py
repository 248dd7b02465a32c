"""Progress output (issue 60: a log of 6 lines was 188 KB of bars): tqdm's bars only on a terminal; in a log,
one line per stage when it ends; nothing with --quiet."""
from __future__ import annotations

import io
import sys

from ssgwarp.core import progress


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def test_a_log_gets_one_line_per_stage(monkeypatch):
    err = _Stream(tty=False)
    monkeypatch.setattr(sys, "stderr", err)
    total = sum(x for x in progress.tqdm(range(200), desc="reconstruct", unit="step"))
    assert total == sum(range(200))
    for _ in progress.tqdm(range(50), desc="loading images", leave=False):     # a sub-step: no line
        pass
    bar = progress.tqdm(total=30, desc="stage 2", unit="step")
    for _ in range(30):
        bar.update(1)
    bar.set_postfix(loss=0.5)
    bar.close()
    bar.close()                                                                   # (closing twice: one line)
    for _ in progress.tqdm(range(10), desc="quiet", disable=True):
        pass
    lines = err.getvalue().splitlines()
    assert len(lines) == 2, lines
    assert lines[0].startswith("ssgwarp: reconstruct: 200/200 step in ") and lines[0].endswith(" s")
    assert lines[1].startswith("ssgwarp: stage 2: 30/30 step in ") and lines[1].endswith("(loss=0.5)")
    assert "\r" not in err.getvalue() and "%|" not in err.getvalue()


def test_a_terminal_gets_tqdms_bar(monkeypatch):
    from tqdm.auto import tqdm

    monkeypatch.setattr(sys, "stderr", _Stream(tty=True))
    bar = progress.tqdm(range(3), desc="x")
    assert isinstance(bar, tqdm)
    bar.close()


def test_the_cli_writes_a_short_log(tmp_path, capsys):
    """A whole command with its stderr not on a terminal (pytest's capture, as a log file): a few lines, no
    bars (was 188 KB for 6 lines)."""
    from ssgwarp import procedural as P
    from ssgwarp.cli import main

    gt = P.build_scene(0.25)
    cams = P.ring_cameras(6, 24, 18)
    images, _ = P.render_views(gt, cams)
    P.write_transforms_dataset(tmp_path / "cap", images, cams)
    capsys.readouterr()
    assert main(["reconstruct", str(tmp_path / "cap"), "--out", str(tmp_path / "run"), "--iters", "30", "--device",
                 "cpu", "--sh-degree", "0", "--init", "random", "--random-points", "300", "--backdrop", "off"]) == 0
    text = capsys.readouterr().err
    assert "%|" not in text and "\r" not in text, text[:500]
    assert any(ln.startswith("ssgwarp: ") and "30/30 step" in ln for ln in text.splitlines()), text
    assert len(text) < 4000, text
