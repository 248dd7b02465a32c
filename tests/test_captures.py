"""benchmarks/captures.py: the capture quality table and its regression flag."""
import json
import sys
from pathlib import Path

import pytest

pytest.importorskip("warp")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import captures  # noqa: E402

LEGO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lego_200"


def test_compare_flags_a_loss_beyond_the_tolerance():
    base = {"cup/7k": {"psnr": 28.4, "iters": 7000}, "fern8/auto": {"psnr": 27.0, "iters": 12000},
            "lego/20": {"psnr": 20.0, "iters": 20}}
    rows = [{"capture": "cup", "setting": "7k", "iters": 7000, "psnr": 28.1},        # -0.3: regression
            {"capture": "fern8", "setting": "auto", "iters": 9000, "psnr": 26.85},   # -0.15: ok (auto's steps vary)
            {"capture": "lego", "setting": "20", "iters": 20, "psnr": 21.0},         # a gain
            {"capture": "bird", "setting": "7k", "iters": 7000, "psnr": 20.0},       # no baseline
            {"capture": "livingroom", "setting": "7k", "iters": 7000, "psnr": None}]
    out = captures.compare(rows, base, tolerance=0.2)
    assert [r["status"] for r in out] == ["REGRESSION", "ok", "ok", "new", "failed"]
    assert out[0]["delta_db"] == pytest.approx(-0.3)
    md = captures.table(out)
    assert md.count("REGRESSION") == 2  # the header's rule and the cup's row
    assert "| cup | 7k |" in md and "**-0.30 REGRESSION**" in md
    # a smoke run's step count only meets a baseline row of the same count
    assert captures.compare([dict(rows[2], iters=40, setting="40")], {"lego/40": {"psnr": 30, "iters": 20}}
                            )[0]["status"] == "new"


@pytest.mark.skipif(not LEGO.is_dir(), reason="needs ../shared/data/lego_200")
def test_smoke_run_writes_table_baseline_and_exit_code(tmp_path, capsys, monkeypatch):
    out, base = tmp_path / "out", tmp_path / "baseline.json"
    smoke = ["--captures", "lego", "--iters", "4", "--max-images", "4", "--width", "40", "--random-points", "400",
             "--device", "cpu", "--out", str(out), "--baseline", str(base), "--no-progress"]
    assert captures.main(smoke + ["--write-baseline"]) == 0
    rows = [json.loads(x) for x in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["capture"] == "lego" and rows[0]["iters"] == 4
    assert rows[0]["resolution"] == "40x40" and rows[0]["test_views"] == 1 and rows[0]["gaussians"] > 0
    assert 5 < rows[0]["psnr"] < 40 and rows[0]["backdrop"]["used"] is False   # white background: no backdrop
    assert not (out / "runs" / "lego-4" / "scene.ply").exists() and (out / "runs" / "lego-4" / "metrics.json").is_file()
    assert "| lego | 4 | 40x40 | 4 |" in (out / "results.md").read_text()
    stored = json.loads(base.read_text())["rows"]
    assert stored["lego/4"]["psnr"] == pytest.approx(rows[0]["psnr"])

    # the same command again: the recorded row is reused, nothing is trained
    monkeypatch.setattr(captures, "run_one", lambda *a, **k: pytest.fail("ran again"))
    capsys.readouterr()
    assert captures.main(smoke) == 0
    assert "| lego | 4 |" in capsys.readouterr().out

    # a baseline 0.5 dB above the run: REGRESSION and exit status 1; 0.1 dB above: within the tolerance
    for above, code in ((0.5, 1), (0.1, 0)):
        base.write_text(json.dumps({"rows": {"lego/4": {"psnr": rows[0]["psnr"] + above, "iters": 4}}}))
        assert captures.main(["--from", str(out / "results.jsonl"), "--baseline", str(base)]) == code
        text = capsys.readouterr().out
        assert ("**-0.50 REGRESSION**" in text) == (code == 1)
