"""benchmarks/host_stages.py splits a call's host time by stage with timers wrapped around the stages'
functions for the run: the split must add up, name each stage, and leave every wrapped function as it
was (a wrapper left behind would slow every later call of the process)."""
import sys
from pathlib import Path

import pytest

pytest.importorskip("warp")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import host_stages as hs  # noqa: E402

from ssgwarp.raster import blend_ops, launch, ops, rasterize  # noqa: E402


def test_stage_split_adds_up_and_the_wrappers_are_removed(tmp_path):
    before = [rasterize.check_shapes, ops.apply, ops.bin_tiles, launch.sort_pairs, launch.finish_read_int64,
              blend_ops.blend_warp, ops._Project.__dict__["forward"], ops._Project.__dict__["backward"],
              blend_ops._Blend.__dict__["forward"], blend_ops._Blend.__dict__["backward"]]
    import torch
    libs = {"ssgwarp": (hs.ssgwarp.rasterization, hs.ssgwarp_stages())}
    res = hs.run_case(16, 16, 16, libs, torch.device("cpu"), rounds=1, calls=3)["ssgwarp"]
    after = [rasterize.check_shapes, ops.apply, ops.bin_tiles, launch.sort_pairs, launch.finish_read_int64,
             blend_ops.blend_warp, ops._Project.__dict__["forward"], ops._Project.__dict__["backward"],
             blend_ops._Blend.__dict__["forward"], blend_ops._Blend.__dict__["backward"]]
    assert all(a is b for a, b in zip(before, after))
    # every stage was timed, inside its parent, and the parts of the forward fit in it
    for label in ("check_shapes", "projection", "projection body", "binning", "sort", "blending",
                  "blending body", "B projection", "B blending"):
        assert res[label] > 0, label
    assert res["projection body"] <= res["projection"] and res["blending body"] <= res["blending"]
    assert res["sort"] <= res["binning"]
    assert res["forward rest"] >= 0 and res["backward rest"] >= 0
    assert res["total"] >= res["forward"] + res["backward"]
    out = tmp_path / "stages.md"
    hs.main(["--device", "cpu", "--cases", "16", "--rounds", "1", "--calls", "2", "--markdown", str(out)])
    text = out.read_text()
    assert all(f"| {stage} |" in text for stage, *_ in hs.ROWS)
