"""benchmarks/stylize_bound.py: the style loss alone on free pixels (how far Stage 2's loss can take the texture
distance), run end to end on a small reconstruction built here."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stylize_bound as sb  # noqa: E402


def test_free_pixels_lower_the_loss_and_leave_the_background_alone():
    g = torch.Generator().manual_seed(0)
    start = torch.rand(2, 12, 10, 3, generator=g) * 0.8 + 0.1
    alphas = torch.zeros(2, 12, 10)
    alphas[:, 2:10, 2:8] = 1.0
    target = torch.tensor([0.9, 0.1, 0.2])

    def loss(img, view, step):
        return ((img - target) ** 2).mean()

    seen = list(sb.free_pixels(start, alphas, loss, [5, 40], lr=0.1))
    assert [c for c, _ in seen] == [5, 40]
    inside = alphas[..., None].expand_as(start) >= 0.5
    errors = [((im - target) ** 2)[inside].mean() for _, im in seen]
    assert errors[0] < ((start - target) ** 2)[inside].mean() and errors[1] < 0.5 * errors[0]
    for _, im in seen:
        assert torch.equal(im[~inside], start[~inside])


def test_style_paths_by_name_by_path_and_bad_names(tmp_path):
    from ssgwarp.errors import InputError

    for name in ("b.png", "a.jpg", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in sb.style_paths("", tmp_path)] == ["a.jpg", "b.png"]
    assert sb.style_paths("b", tmp_path) == [tmp_path / "b.png"]
    assert sb.style_paths(str(tmp_path / "a.jpg"), tmp_path / "missing") == [tmp_path / "a.jpg"]
    with pytest.raises(InputError, match="'c': not a file"):
        sb.style_paths("a,c", tmp_path)
    with pytest.raises(InputError, match="no style images"):
        sb.style_paths("", tmp_path / "missing")


def _run(tmp_path):
    from ssgwarp.core.fileio import write_image
    from test_grouping import blobs_scene, make_run, ring_cameras

    scene, _ = blobs_scene()
    run = make_run(tmp_path / "run", scene, ring_cameras(n=10, size=24))
    yy, xx = np.meshgrid(np.arange(32), np.arange(32), indexing="ij")
    stripes = np.where(((xx + yy) // 3 % 2 == 0)[..., None], [0.95, 0.85, 0.1], [0.1, 0.15, 0.6]).astype(np.float32)
    write_image(tmp_path / "stripes.png", stripes)
    return run, tmp_path / "stripes.png"


def test_main_scores_free_pixels_per_step_count(tmp_path, monkeypatch, capsys):
    run, style = _run(tmp_path)
    out = tmp_path / "bound.json"
    monkeypatch.setattr(sys, "argv", ["stylize_bound.py", "--run", str(run), "--styles", str(style),
                                      "--steps", "150,0", "--frames", "2", "--device", "cpu", "--json", str(out)])
    assert sb.main() == 0
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
def test_main_bad_flags_are_one_line_errors(tmp_path, monkeypatch, capsys, flags, says):
    monkeypatch.setattr(sys, "argv", ["stylize_bound.py", "--run", str(tmp_path), "--style-dir", str(tmp_path), *flags])
    assert sb.main() == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err


def test_main_a_folder_that_is_no_run_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    (tmp_path / "s.png").write_bytes(b"x")
    monkeypatch.setattr(sys, "argv", ["stylize_bound.py", "--run", str(tmp_path / "nothing"), "--styles",
                                      str(tmp_path / "s.png"), "--device", "cpu"])
    assert sb.main() == 2
    err = capsys.readouterr().err.strip()
    assert "nothing" in err and "ssgwarp reconstruct" in err and "\n" not in err
