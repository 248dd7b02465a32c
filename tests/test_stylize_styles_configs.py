"""benchmarks/stylize_styles.py --configs: the file of ``TAG: FLAGS`` lines it reads, and --timeout counted from
the command's start (the scene it builds first included), so a run under a device's per-call limit stops in time."""
import argparse
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stylize_styles as ss  # noqa: E402


def test_configs_file_is_read_with_comments_and_quoting(tmp_path):
    f = tmp_path / "c.txt"
    f.write_text("# a comment\n\nc0: --mode global --content-weight 0  # trailing\n"
                 "b.2_x: --tag-like 'two words'\n")
    assert ss.parse_configs(f) == [("c0", ["--mode", "global", "--content-weight", "0"]),
                                   ("b.2_x", ["--tag-like", "two words"])]


@pytest.mark.parametrize("text, says", [("no colon here\n", "expected 'TAG: FLAGS'"),
                                        ("bad tag: --x\n", "expected 'TAG: FLAGS'"),
                                        ("a: --x\na: --y\n", "a TAG appears twice"),
                                        ("# only a comment\n", "no configuration")])
def test_bad_configs_files_are_refused_with_the_line(tmp_path, text, says):
    f = tmp_path / "c.txt"
    f.write_text(text)
    with pytest.raises(SystemExit, match=says):
        ss.parse_configs(f)


class _FakeProcess:
    """A configuration's process that never finishes by itself: waits until the timeout it is given."""
    waits: list = []

    def __init__(self, cmd, stdout=None, stderr=None):
        self.cmd, self.terminated = cmd, False
        stdout.close()

    def wait(self, timeout=None):
        if self.terminated:
            return -15
        _FakeProcess.waits.append(timeout)
        raise subprocess.TimeoutExpired(self.cmd, timeout)

    def terminate(self):
        self.terminated = True


def test_timeout_counts_the_scene_build(tmp_path, monkeypatch, capsys):
    cfg = tmp_path / "c.txt"
    cfg.write_text("a: --content-weight 0\nb: --content-weight 0.01\n")
    monkeypatch.setattr(ss, "prepare_scene", lambda *a, **k: time.sleep(0.6))
    monkeypatch.setattr(subprocess, "Popen", _FakeProcess)
    _FakeProcess.waits = []
    args = argparse.Namespace(configs=cfg, scene="demo", out=tmp_path, fern_iters=1, demo_size="small",
                              fern=tmp_path, styles=tmp_path, styles_subset=None, path_frames=6, timeout=2.0)
    (tmp_path / "demo_a" / "styles" / "candy").mkdir(parents=True)
    (tmp_path / "demo_a" / "styles" / "candy" / "result.json").write_text("{}")
    assert ss.run_configs(args, [tmp_path / "candy.jpg", tmp_path / "udnie.jpg"], "cpu", False) == 0
    first, second = _FakeProcess.waits
    assert first <= 2.0 - 0.6 + 0.05   # the 0.6 s spent building the scene came off the 2 s
    assert second <= first
    out = capsys.readouterr().out
    assert "== a (exit -15): 1/2 styles finished" in out and "== b (exit -15): 0/2 styles finished" in out


def test_half_style_references_are_computed_once_and_kept_with_the_result(tmp_path, monkeypatch):
    """``--report`` re-reads every finished style: the half-of-the-style reference is stored in the style's
    result.json the first time, not recomputed on every report."""
    import json

    import torch

    from ssgwarp.core.cameras import Cameras
    from ssgwarp.core.fileio import write_image, write_json
    from ssgwarp.evaluation.style_distance import StyleDistance

    run = tmp_path / "run"
    run.mkdir()
    Cameras(torch.eye(4)[None], torch.tensor([[[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]]]), 32, 24).save(
        run / "cameras.json")
    write_image(tmp_path / "candy.png", torch.rand(40, 50, 3))
    res = tmp_path / "styles" / "candy"
    res.mkdir(parents=True)
    write_json(res / "result.json", {"style": "candy", "texture_after": 1.0})
    calls = []
    real = StyleDistance.halves
    monkeypatch.setattr(StyleDistance, "halves", lambda self, h, w: calls.append((h, w)) or real(self, h, w))
    for _ in range(2):
        rows = [json.loads((res / "result.json").read_text())]
        ss.add_halves(rows, [tmp_path / "candy.png"], run, tmp_path / "styles")
        assert rows[0]["texture_half"] > 0 and rows[0]["color_half"] > 0 and rows[0]["texture_after"] == 1.0
    assert calls == [(24, 32)]                      # once, at the views' size
    assert json.loads((res / "result.json").read_text())["texture_half"] == rows[0]["texture_half"]


def test_stage2_config_takes_the_stage2_options_given_and_overrides():
    from ssgwarp.stylization.stage2 import Stage2Config

    args = argparse.Namespace(scene="demo", tag="x", iters=7, lr=None, mode="global", consistency_budget=1.6,
                              style_scale=None)
    cfg = ss.stage2_config(args, tv_weight=0.1)
    assert cfg == Stage2Config(iters=7, mode="global", consistency_budget=1.6, tv_weight=0.1)
    assert ss.stage2_config(argparse.Namespace()) == Stage2Config()


def test_an_unknown_style_name_stops_the_run_with_one_line(tmp_path, monkeypatch):
    (tmp_path / "candy.jpg").write_bytes(b"x")
    monkeypatch.setattr(ss, "prepare_scene", lambda *a, **k: pytest.fail("no scene is built for a bad style name"))
    monkeypatch.setattr(sys, "argv", ["stylize_styles.py", "--scene", "demo", "--styles", str(tmp_path),
                                      "--styles-subset", "candy,cnady", "--out", str(tmp_path / "out")])
    with pytest.raises(SystemExit, match="style 'cnady': not a file and not an image in"):
        ss.main()
    assert not (tmp_path / "out").exists()
