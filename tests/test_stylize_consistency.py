"""benchmarks/stylize_consistency.py: the probe texture fixed in 3-D and the demo's true scene it can be scored on."""
import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import stylize_consistency as sc  # noqa: E402


def test_demo_truth_is_the_procedural_scene_of_the_demos_size_and_seed(tmp_path):
    from ssgwarp import procedural as P
    from ssgwarp.errors import InputError

    (tmp_path / "scene").mkdir()
    with pytest.raises(InputError, match="summary.json not found"):
        sc.demo_truth(tmp_path / "scene")
    (tmp_path / "summary.json").write_text(json.dumps({"size": "huge", "seed": 0}))
    with pytest.raises(InputError, match="demo size 'huge'"):
        sc.demo_truth(tmp_path / "scene")
    (tmp_path / "summary.json").write_text(json.dumps({"size": "small", "seed": 3}))
    truth = sc.demo_truth(tmp_path / "scene")
    expected = P.build_scene(P.SIZES["small"].density, seed=3).scene
    assert torch.equal(truth.means, expected.means) and torch.equal(truth.sh_dc, expected.sh_dc)
    assert not torch.equal(truth.means, P.build_scene(P.SIZES["small"].density, seed=0).scene.means)


def test_probe_is_a_function_of_position_with_the_asked_contrast():
    from ssgwarp import procedural as P
    from ssgwarp.raster.scene import SH_C0

    scene = P.build_scene(0.5, seed=0).scene
    painted = sc.probe_scene(scene, period_px=4, amplitude=0.2, pixel=0.01)
    added = (painted.sh_dc - scene.sh_dc).reshape(len(scene), 3) * SH_C0
    assert torch.allclose(added[:, 0], added[:, 1]) and torch.allclose(added[:, 0], added[:, 2])   # grey
    assert 0.1 < float(added[:, 0].std()) < 0.3
    assert torch.equal(painted.means, scene.means)
    again = sc.probe_scene(scene, period_px=4, amplitude=0.2, pixel=0.01)
    assert torch.equal(again.sh_dc, painted.sh_dc)


def test_bad_run_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["stylize_consistency.py", "--run", str(tmp_path), "--truth", "--device", "cpu"])
    assert sc.main() == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("stylize_consistency: ") and "no scene.ply" in err and "\n" not in err
