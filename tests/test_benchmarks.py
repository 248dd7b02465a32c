"""benchmarks/: at most ten scripts and 3,500 lines, each one's ``--help`` (and each mode's) exits 0 on the CPU, and the shared
harness (data location, timing statistics, tables, JSON lines) does what the tools rely on."""
import json
import runpy
import sys
from pathlib import Path

import pytest
import torch

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))
import harness  # noqa: E402

MODES = {"train_step.py": ["runs", "loss"], "stylize.py": ["captures", "stage2", "probe", "bound"], "tradeoffs.py": ["budget"],
         "captures.py": ["appearance", "inside-out"]}


def test_at_most_ten_scripts_and_every_help_exits_0(monkeypatch, capsys):
    scripts = sorted(p.name for p in BENCH.glob("*.py"))
    assert len(scripts) <= 10, scripts
    lines = {p.name: len(p.read_text().splitlines()) for p in BENCH.iterdir() if p.is_file()}
    assert sum(lines.values()) <= 3500, lines          # everything in the folder, the baseline file included
    calls = [[s, "--help"] for s in scripts] + [[s, m, "--help"] for s, ms in MODES.items() for m in ms]
    # in this process (torch and ssgwarp are imported once): each script run as __main__ with its argv, as
    # `python benchmarks/X.py ...` runs it, on the CPU
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for argv in calls:
        monkeypatch.setattr(sys, "argv", argv)
        try:
            runpy.run_path(str(BENCH / argv[0]), run_name="__main__")
            code = 0
        except SystemExit as e:
            code = e.code or 0
        text = capsys.readouterr().out
        assert code == 0, (argv, text[-500:])
        if argv[0] != "harness.py":
            assert "usage:" in text, argv          # argparse printed the help (not a run that happened to exit 0)


def test_data_root_is_the_first_existing_candidate(tmp_path, monkeypatch):
    monkeypatch.setattr(harness, "CANDIDATES", (tmp_path / "missing", tmp_path))
    assert harness.data_root() == tmp_path
    monkeypatch.setattr(harness, "CANDIDATES", (tmp_path / "a", tmp_path / "b"))
    assert harness.data_root() == tmp_path / "a"      # none exists: the first, for the error message


def test_style_paths_by_name_by_path_and_bad_names(tmp_path):
    from ssgwarp.errors import InputError

    for name in ("b.png", "a.jpg", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in harness.style_paths("", tmp_path)] == ["a.jpg", "b.png"]
    assert harness.style_paths("b", tmp_path) == [tmp_path / "b.png"]
    assert harness.style_paths(str(tmp_path / "a.jpg"), tmp_path / "missing") == [tmp_path / "a.jpg"]
    with pytest.raises(InputError, match="'c': not a file"):
        harness.style_paths("a,c", tmp_path)
    with pytest.raises(InputError, match="no style images"):
        harness.style_paths("", tmp_path / "missing")


def test_measure_warms_up_then_times_each_repeat():
    calls = []
    ticks = iter(range(100))
    s = harness.measure(lambda: calls.append(1), "cpu", repeats=3, warmup=2, clock=lambda: next(ticks) / 1e3)
    assert len(calls) == 5 and s == {"median": 1.0, "min": 1.0, "max": 1.0, "n": 3}
    assert harness.stats([3.0, 1.0, 2.0, 10.0]) == {"median": 2.5, "min": 1.0, "max": 10.0, "n": 4}
    order = []
    t = harness.interleaved({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, "cpu", 4, rounds=2)
    assert order == ["a", "b"] + ["a", "a", "b", "b"] * 2 and t["a"]["n"] == t["b"]["n"] == 4


def test_table_and_json_lines(tmp_path):
    rows = [{"n": 10000, "ms": 1.234, "tiny": 1e-5, "x": None}, {"n": 5, "ms": float("nan"), "name": "b"}]
    text = harness.table(rows, [("n", "N"), ("ms", "ms"), ("tiny", "err"), ("never", "left out"), ("name", "name")])
    assert text.splitlines() == ["| N | ms | err | name |", "|---|---|---|---|",
                                 "| 10,000 | 1.23 | 1.00e-05 | - |", "| 5 | - | - | b |"]
    harness.append_jsonl(tmp_path / "d" / "r.jsonl", rows[0])
    harness.append_jsonl(tmp_path / "d" / "r.jsonl", {"n": 2})
    harness.append_jsonl(None, {"n": 3})
    lines = (tmp_path / "d" / "r.jsonl").read_text().splitlines()
    assert [json.loads(x)["n"] for x in lines] == [10000, 2]
    assert "torch" in harness.header("cpu") and "cores" in harness.machine("cpu")


def test_capture_folder_by_name_or_path(tmp_path):
    from ssgwarp.errors import InputError

    (tmp_path / "llff_fern").mkdir()
    assert harness.capture_folder("fern4", tmp_path) == (tmp_path / "llff_fern", "images_4")
    assert harness.capture_folder(f"{tmp_path}:images_2") == (tmp_path, "images_2")
    assert harness.capture_folder(str(tmp_path)) == (tmp_path, "images")
    with pytest.raises(InputError, match="capture 'cup'.*shared captures: fern8"):
        harness.capture_folder("cup", tmp_path)


def test_raster_cases_by_set_or_spec():
    import raster

    assert raster.parse_cases(["quick"]) == raster.CASES["quick"]
    assert raster.parse_cases(["1000x64x48", "2000x32x32:3:4", "ball2:500x64x48"]) == [
        (1000, 64, 48, None, 1), (2000, 32, 32, 3, 4), (500, 64, 48, 3, 1, "ball2")]
    with pytest.raises(SystemExit, match="neither"):
        raster.parse_cases(["10kx64"])


def test_knobs_go_to_the_first_target_with_the_field_typed_as_its_value():
    from dataclasses import dataclass

    from ssgwarp.errors import InputError

    @dataclass
    class A:
        x: float = 1.0
        n: int = 2
        on: bool = False
        name: str = "a"
        opt: object = None

    @dataclass
    class B:
        x: int = 0
        k: int = 0

    a, b = harness.knobs(["x=1", "n=3", "on=true", "name=7", "k=-4", "opt=2.5", " "], A(), B())
    assert a == {"x": 1.0, "n": 3, "on": True, "name": "7", "opt": 2.5} and b == {"k": -4}
    assert type(a["x"]) is float and type(a["n"]) is int
    with pytest.raises(InputError, match="zz=1: no such field of A or B"):
        harness.knobs(["zz=1"], A(), B())
    with pytest.raises(InputError, match="k=lots: B.k takes a number"):
        harness.knobs(["k=lots"], A(), B())
