"""benchmarks/stylize.py: the styles table's --configs file (``TAG: FLAGS`` lines) and --timeout counted from the
command's start (the scene it builds first included); the ``bound`` mode (the style loss alone on free pixels, run
end to end on a small reconstruction built here); the ``probe`` mode (texture fixed in 3-D, the demo's true scene)."""
import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stylize as ss  # noqa: E402


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


def test_an_unknown_style_name_stops_the_run_with_one_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "candy.jpg").write_bytes(b"x")
    monkeypatch.setattr(ss, "prepare_scene", lambda *a, **k: pytest.fail("no scene is built for a bad style name"))
    assert ss.main(["--scene", "demo", "--styles", str(tmp_path), "--styles-subset", "candy,cnady",
                    "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stylize.py: style 'cnady': not a file and not an image in") and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_bound_free_pixels_lower_the_loss_and_leave_the_background_alone():
    g = torch.Generator().manual_seed(0)
    start = torch.rand(2, 12, 10, 3, generator=g) * 0.8 + 0.1
    alphas = torch.zeros(2, 12, 10)
    alphas[:, 2:10, 2:8] = 1.0
    target = torch.tensor([0.9, 0.1, 0.2])

    def loss(img, view, step):
        return ((img - target) ** 2).mean()

    seen = list(ss.free_pixels(start, alphas, loss, [5, 40], lr=0.1))
    assert [c for c, _ in seen] == [5, 40]
    inside = alphas[..., None].expand_as(start) >= 0.5
    errors = [((im - target) ** 2)[inside].mean() for _, im in seen]
    assert errors[0] < ((start - target) ** 2)[inside].mean() and errors[1] < 0.5 * errors[0]
    for _, im in seen:
        assert torch.equal(im[~inside], start[~inside])


def _run(tmp_path):
    from ssgwarp.core.fileio import write_image
    from test_grouping import blobs_scene, make_run, ring_cameras

    scene, _ = blobs_scene()
    run = make_run(tmp_path / "run", scene, ring_cameras(n=10, size=24))
    yy, xx = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    stripes = np.where(((xx + yy) // 3 % 2 == 0)[..., None], [0.95, 0.85, 0.1], [0.1, 0.15, 0.6]).astype(np.float32)
    write_image(tmp_path / "stripes.png", stripes)
    return run, tmp_path / "stripes.png"


def test_bound_scores_free_pixels_per_step_count(tmp_path, monkeypatch, capsys):
    run, style = _run(tmp_path)
    out = tmp_path / "bound.json"
    assert ss.main(["bound", "--run", str(run), "--styles", str(style), "--steps", "150,0", "--frames", "2",
                    "--device", "cpu", "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["steps"] == [0, 150] and rec["views"] == 2 and len(rec["rows"]) == 1
    row = rec["rows"][0]
    assert row["style"] == "stripes"
    assert row["free"]["0"] == pytest.approx(row["color_transfer"], rel=1e-5)   # 0 steps: the colour transfer
    assert row["free"]["150"] < 0.7 * row["free"]["0"]                          # the loss paints texture
    table = capsys.readouterr().out
    assert "| stripes |" in table and "**mean of 1**" in table and "150 steps / view" in table


@pytest.mark.parametrize("flags, says", [(["--steps", "ten"], "--steps takes step counts"),
                                         (["--steps=-1,5"], "--steps takes step counts"),
                                         (["--styles", "nope"], "style 'nope': not a file")])
def test_bound_bad_flags_are_one_line_errors(tmp_path, monkeypatch, capsys, flags, says):
    assert ss.main(["bound", "--run", str(tmp_path), "--style-dir", str(tmp_path), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err


def test_bound_a_folder_that_is_no_run_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    (tmp_path / "s.png").write_bytes(b"x")
    assert ss.main(["bound", "--run", str(tmp_path / "nothing"), "--styles", str(tmp_path / "s.png"),
                    "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert "nothing" in err and "ssgwarp reconstruct" in err and "\n" not in err


def test_probe_demo_truth_is_the_procedural_scene_of_the_demos_size_and_seed(tmp_path):
    from ssgwarp import procedural as P
    from ssgwarp.errors import InputError

    (tmp_path / "scene").mkdir()
    with pytest.raises(InputError, match="summary.json not found"):
        ss.demo_truth(tmp_path / "scene")
    (tmp_path / "summary.json").write_text(json.dumps({"size": "huge", "seed": 0}))
    with pytest.raises(InputError, match="demo size 'huge'"):
        ss.demo_truth(tmp_path / "scene")
    (tmp_path / "summary.json").write_text(json.dumps({"size": "small", "seed": 3}))
    truth = ss.demo_truth(tmp_path / "scene")
    expected = P.build_scene(P.SIZES["small"].density, seed=3).scene
    assert torch.equal(truth.means, expected.means) and torch.equal(truth.sh_dc, expected.sh_dc)
    assert not torch.equal(truth.means, P.build_scene(P.SIZES["small"].density, seed=0).scene.means)


def test_probe_is_a_function_of_position_with_the_asked_contrast():
    from ssgwarp import procedural as P
    from ssgwarp.raster.scene import SH_C0

    scene = P.build_scene(0.5, seed=0).scene
    painted = ss.probe_scene(scene, period_px=4, amplitude=0.2, pixel=0.01)
    added = (painted.sh_dc - scene.sh_dc).reshape(len(scene), 3) * SH_C0
    assert torch.allclose(added[:, 0], added[:, 1]) and torch.allclose(added[:, 0], added[:, 2])   # grey
    assert 0.1 < float(added[:, 0].std()) < 0.3
    assert torch.equal(painted.means, scene.means)
    again = ss.probe_scene(scene, period_px=4, amplitude=0.2, pixel=0.01)
    assert torch.equal(again.sh_dc, painted.sh_dc)


def test_probe_bad_run_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    assert ss.main(["probe", "--run", str(tmp_path), "--truth", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stylize.py probe: ") and "no scene.ply" in err and "\n" not in err


def test_capture_summary_names_the_styles_that_move_away():
    rows = [{"style": "candy", "color_before": 10.0, "color_after": 5.0, "texture_before": 1.0, "texture_after": 0.5,
             "short": 0.02, "long": 0.03},
            {"style": "the_resevoir", "color_before": 10.0, "color_after": 9.0, "texture_before": 1.0,
             "texture_after": 1.08, "short": 0.03, "long": 0.03}]
    row = ss.capture_row("livingroom", rows, {"short": 0.02, "long": 0.03})
    assert row["farther"] == "the_resevoir (1.08)" and row["styles"] == 2
    assert row["colour"] == "-30.0 %" and row["texture"] == "-21.0 %" and row["consistency"] == "1.50 / 1.00"


def test_captures_reconstructs_once_and_keeps_its_tables_apart_from_the_run(tmp_path, monkeypatch, capsys):
    import ssgwarp.cli
    import ssgwarp.stylization.spread as spread

    (tmp_path / "cap").mkdir()
    built, tabled = [], []

    def fake_cli(argv):
        run = Path(argv[argv.index("--out") + 1])
        (run / "groups").mkdir(parents=True)
        (run / "groups" / "classifier.pt").write_bytes(b"")
        built.append(argv)
        return 0

    def fake_styles(argv):
        scene, out = Path(argv[argv.index("--scene") + 1]), Path(argv[argv.index("--out") + 1])
        res = out / f"{scene.name}_t"
        assert res != scene and not str(res).startswith(str(scene) + "/")
        res.mkdir(parents=True, exist_ok=True)
        row = {"style": "candy", "color_before": 2.0, "color_after": 1.0, "texture_before": 1.0, "texture_after": 0.5,
               "short": 0.01, "long": 0.01}
        (res / "results.json").write_text(json.dumps({"rows": [row], "source": {"short": 0.01, "long": 0.01}}))
        tabled.append(argv)

    monkeypatch.setattr(ssgwarp.cli, "main", fake_cli)
    monkeypatch.setattr(ss, "styles_main", fake_styles)
    monkeypatch.setattr(ss, "load_run", lambda *a, **k: (torch.zeros(1), argparse.Namespace(
        cameras=torch.zeros(2), train_ids=[0, 1])))
    monkeypatch.setattr(spread, "consistency_probe", lambda scene, cams: 1.5)
    argv = ["--captures", str(tmp_path / "cap"), "--out", str(tmp_path / "o"), "--tag", "t", "--device", "cpu",
            "--iters", "3"]
    assert ss.captures_main(argv) == 0 and ss.captures_main(argv) == 0
    assert len(built) == 1 and all("--iters" in a and "3" in a for a in tabled) and len(tabled) == 2
    text = (tmp_path / "o" / "captures_t.md").read_text()
    assert "| cap | 1 | -50.0 % | -50.0 % | none | 1.00 / 1.00 | 1.50 |" in text
