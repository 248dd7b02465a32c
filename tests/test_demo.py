"""`ssgwarp demo`, and the procedural scene it is built on.

The default demo (what the README shows) runs once per session through the CLI (~25-60 s on 2
cores), with every download function replaced by one that records the attempt; the tests read what it
wrote and printed: its printed numbers are the README's (docs/make_figures.py wrote them), it made no
download attempt, the NeRF capture reads back with the cameras it was rendered from (OpenGL axes), every
stage wrote the run contract, the summary's numbers are what the stages measured, an existing demo is
never overwritten without --force. A `small` demo interrupted by Ctrl-C resumes to the same scene.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ssgwarp import procedural as P

WEIGHT_VARS = ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
               "SSGWARP_IMAGE_ENCODER", "SSGWARP_VGG16", "SSGWARP_RAFT", "SSGWARP_LPIPS")


def _no_weights(mp: pytest.MonkeyPatch) -> None:
    for v in WEIGHT_VARS:
        mp.delenv(v, raising=False)


def _main(argv):
    from ssgwarp.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="session")
def demo(tmp_path_factory):
    """The default demo run once through the CLI, as the README says: (out folder, exit code, stdout, stderr,
    download attempts). Every function that could download is replaced by one that records the call."""
    from ssgwarp.services import weights as W

    out = tmp_path_factory.mktemp("demo") / "demo"
    attempts: list = []
    with pytest.MonkeyPatch.context() as mp:
        _no_weights(mp)
        for name in ("fetch", "_hf_download", "_url_download", "_hub_files", "_url_size"):
            if hasattr(W, name):
                mp.setattr(W, name, lambda *a, _n=name, **k: attempts.append((_n, a)) or (_ for _ in ()).throw(
                    RuntimeError(f"the demo tried to download ({_n})")))
        code, stdout, stderr = _main(["demo", "--out", out, "--quiet", "--device", "cpu"])
    return out, code, stdout, stderr, attempts


# ----------------------------------------------------------------------------- the demo
@pytest.mark.slow  # the demo fixture runs the default demo once per session (~25-60 s on 2 cores)
def test_demo_runs_every_stage_and_prints_a_summary(demo):
    out, code, stdout, stderr, _ = demo
    assert code == 0, stderr
    summary = json.loads((out / "summary.json").read_text())
    record = json.loads((out / "demo.json").read_text())
    assert [s for s in record["stages"]] == ["data", "reconstruct", "group", "stylize", "evaluate", "sheet"]
    assert all(v["done"] for v in record["stages"].values())
    # the printed summary names every stage, Stage 1's skip and the contact sheet
    for word in ("reconstruct", "mask-free clusters", "key views", "Stage 1 (diffusion)", "Stage 2 (IST)",
                 "evaluate", "held-out PSNR", "Gram style loss", "consistency RMSE"):
        assert word in stdout, word
    assert "skipped: no local weights for sd15, controlnet_depth, ip_adapter, image_encoder" in stdout
    assert "%|" not in stderr                       # --quiet: no progress bars, the evaluation's included
    assert summary["stage1"]["ran"] is False and "Stage 1 did not run" in summary["matching"]
    # which Stage 2 path ran: weight-free here (no VGG16, no Stage 1), said in the output and the summary
    assert "Stage 2 path: weight-free (no Stage 1, random features random-multiscale" in stdout
    assert summary["weight_free"] is True and summary["style_loss"] == "sw" and summary["color_transfer"] == "both"
    # ... and it moves the scene toward the style by the weight-free distances (measured 2026-11-28 on the
    # default demo, 40 Stage 2 steps: colour x0.70, texture x0.60; asserted with margin; the README states the numbers)
    for k in ("color", "texture"):
        assert 0 < summary["style_distance"][k] < 0.85 * summary["style_distance_original"][k], (k, summary)
    last = stdout.strip().splitlines()[-1]
    assert last == f"contact sheet: {summary['contact_sheet']}"
    sheet = Path(summary["contact_sheet"])
    assert sheet == (out / "contact_sheet.png").resolve() and sheet.is_file()
    from ssgwarp.core.fileio import read_image

    img = read_image(sheet, 3)
    assert img.shape[1] > 600 and img.shape[0] > 300 and float(img.std()) > 0.1  # a picture, not a blank
    # the numbers are the stages' own (read back from their files), and sensible
    rec = json.loads((out / "scene" / "metrics.json").read_text())
    sty = json.loads((out / "stylized" / "metrics.json").read_text())
    groups = json.loads((out / "scene" / "groups" / "groups.json").read_text())
    assert summary["gaussians"] == rec["num_gaussians"] and summary["psnr"] == rec["psnr"]
    assert summary["psnr"] > 30.0                     # measured 32.3 dB (2026-11-28, 2 CPU cores)
    assert summary["groups"] == groups["num_groups"] >= 2
    # no Segment Anything weights here: the groups are mask-free clusters, and the summary says so
    assert summary["group_kind"] == groups["kind"] == "mask-free clusters"
    # the five objects, each in a group of its own (issue 38: the neighbour graph in two pieces gave K = 2)
    assert summary["groups"] == 5 and summary["objects_separated"] == 5 and summary["group_purity"] >= 0.95
    assert summary["cross_view_agreement"] > 0.95
    assert summary["gram_style_loss"] == sty["gram_style_loss"] and math.isfinite(summary["content_loss"])
    c = summary["consistency_rmse"]
    assert c["stylized"]["short"] == sty["evaluation"]["consistency"]["reprojection"]["short"]["rmse"]
    # measured RMSE (2026-11-28, the 80x60 demo): reconstruction 0.019 (short) / 0.057 (long), stylized 0.025 /
    # 0.080 (the 96x72 demo with 200 Stage 2 steps: 0.018 / 0.054 and 0.023 / 0.069): a consistent scene, and
    # stylization costs little consistency
    assert all(0.0 < c[r]["short"] < 0.1 and 0.0 < c[r]["long"] < 0.12 for r in c)
    assert all(c["stylized"][k] < c["reconstruction"][k] + 0.03 for k in ("short", "long"))
    assert set(summary["seconds"]) == {"data", "reconstruct", "group", "stylize", "evaluate", "sheet"}
    assert (out / "evaluation.md").read_text().startswith("Evaluation")


@pytest.mark.slow  # the demo fixture runs the default demo once per session
def test_demo_outputs_follow_the_run_contract(demo):
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.services.runs import load_run
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.formats.ply import read_ply

    out = demo[0]
    size = P.SIZES["default"]
    data = load_dataset(out / "data")
    assert len(data) == size.views and (data.width, data.height) == (size.width, size.height)
    scene, run = load_run(out / "scene", "cpu")
    assert run.names == data.names and torch.equal(run.images, data.images)
    gm = load_groups(out / "scene", "cpu")
    assert scene.identities is not None and scene.identities.shape[1] == gm.dim
    styled = read_ply(out / "stylized" / "scene.ply")
    # Stage 2 changed colour only
    assert torch.equal(styled.means, scene.means) and torch.equal(styled.identities, scene.identities)
    assert not torch.equal(styled.sh_dc, scene.sh_dc)
    from ssgwarp.core.fileio import read_image

    style = read_image(out / "style.png", 3)
    assert np.allclose(style, P.style_image(192, 192, seed=0), atol=1 / 255)


@pytest.mark.slow  # the demo fixture runs the default demo once per session
def test_existing_demo_is_not_overwritten_without_force(demo, tmp_path):
    out = demo[0]
    before = _digest(out)
    code, stdout, stderr = _main(["demo", "--out", out, "--quiet", "--device", "cpu"])
    assert code == 2 and "already holds a demo run" in stderr and "--force" in stderr
    assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr
    assert _digest(out) == before
    # --resume with other options is refused too, before anything is written
    code, _, stderr = _main(["demo", "--out", out, "--size", "small", "--resume", "--quiet", "--device", "cpu"])
    assert code == 2 and "other options" in stderr and _digest(out) == before


ROOT = Path(__file__).resolve().parent.parent


def _printed_claims(stdout: str) -> dict:
    """The README's numbers as the demo printed them (its summary lines, not summary.json)."""
    import re

    from ssgwarp.demo import _NUM as num

    g = re.search(rf"K=(\d+) \S.*purity vs true objects {num}, (\d+)/(\d+) objects separated", stdout)
    d = re.search(rf"style distance colour {num} -> {num}, texture {num} -> {num};", stdout)
    assert g and d, stdout
    return {"groups": int(g[1]), "purity": float(g[2]), "separated": int(g[3]), "objects": int(g[4]),
            "color0": float(d[1]), "color1": float(d[2]), "texture0": float(d[3]), "texture1": float(d[4])}


def _stated(path: Path) -> dict:
    """The numbers docs/make_figures.py wrote between the figures markers of ``path``."""
    from ssgwarp.demo import parse_claims

    text = path.read_text()
    start = text.index("<!-- figures:demo -->")
    return parse_claims(text[start:text.index("<!-- /figures -->", start)])


@pytest.mark.slow  # the demo fixture runs the default demo once per session
def test_the_demo_prints_what_the_readme_states(demo):
    """The README's and docs/demo.md's demo numbers (groups, objects separated, purity, style distances) are
    what a fresh default demo prints, within ssgwarp.demo.CLAIM_TOLERANCE (`python docs/make_figures.py`
    rewrites them from a run)."""
    from ssgwarp.demo import claims_hold

    out, code, stdout, stderr, _ = demo
    assert code == 0, stderr
    printed = _printed_claims(stdout)
    readme = _stated(ROOT / "README.md")
    assert _stated(ROOT / "docs" / "demo.md") == readme
    assert claims_hold(readme, printed) == [], (readme, printed)
    assert printed["groups"] == 5 and printed["separated"] == 5 and printed["purity"] >= 0.95


def test_claims_round_trip_and_tolerance():
    from ssgwarp.demo import claims, claims_hold, claims_text, parse_claims

    s = {"groups": 5, "objects_separated": 5, "objects": ["a"] * 5, "group_purity": 0.9931,
         "style_distance_original": {"color": 19.46, "texture": 3.071},
         "style_distance": {"color": 12.94, "texture": 2.152}}
    text = claims_text(s)
    got = parse_claims("before " + text.replace(" ", "\n", 3) + ". After.")
    assert got == {"groups": 5, "separated": 5, "objects": 5, "purity": 0.99, "color0": 19.5, "color1": 12.9,
                   "texture0": 3.07, "texture1": 2.15}
    assert claims_hold(got, claims(s)) == []
    moved = dict(s, style_distance={"color": 14.0, "texture": 2.152}, groups=2, group_purity=0.74)
    bad = claims_hold(got, claims(moved))
    assert [b.split(":")[0] for b in bad] == ["groups", "purity", "style distance color1"]
    with pytest.raises(ValueError):
        parse_claims("K = 5 groups")


def test_make_figures_rewrites_only_the_marked_spans(tmp_path):
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_figures", ROOT / "docs" / "make_figures.py")
    mf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mf)
    text = "a <!-- figures:demo -->old\nnumbers<!-- /figures --> b <!-- figures:demo-table -->t<!-- /figures --> c"
    assert mf.span(text, "demo", "new", tmp_path) == ("a <!-- figures:demo -->new<!-- /figures --> b "
                                                      "<!-- figures:demo-table -->t<!-- /figures --> c")
    with pytest.raises(SystemExit, match="no <!-- figures:demo --> ... <!-- /figures --> span"):
        mf.span("no markers", "demo", "new", tmp_path / "README.md")
    # the files it writes have their markers (it checks them before running the demo)
    for f in mf.CLAIM_FILES:
        mf.span(f.read_text(), "demo", "", f)
    mf.span(mf.TABLE_FILE.read_text(), "demo-table", "", mf.TABLE_FILE)


@pytest.mark.slow  # the demo fixture runs the default demo once per session
def test_the_demo_makes_no_download_attempt(demo):
    out, code, stdout, stderr, attempts = demo
    assert code == 0, stderr
    assert attempts == [] and "downloading" not in stderr


def test_every_demo_stage_runs_with_downloads_off(tmp_path, monkeypatch):
    """Downloads are off from the first stage on (not only while the demo's context is made), and on again
    after the demo."""
    import ssgwarp.demo as D
    from ssgwarp.services import weights as W

    for v in ("SSGWARP_OFFLINE", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        monkeypatch.delenv(v, raising=False)
    seen = {}

    class Stop(Exception):
        pass

    def first_stage(d):
        seen["reason"] = W.offline_reason()
        raise Stop

    monkeypatch.setattr(D, "_stage_data", first_stage)
    before = W.offline_reason()
    with pytest.raises(Stop):
        D.run_demo(tmp_path / "d", "small", device="cpu", progress=False)
    assert seen["reason"] == D.OFFLINE_REASON
    assert W.offline_reason() == before


def test_demo_resume_with_other_options_names_them(tmp_path):
    """(the resume record every command shares: ssgwarp.services.runs.check_resume)"""
    from ssgwarp.core.fileio import write_json
    from ssgwarp.demo import _prepare_out
    from ssgwarp.errors import InputError

    out = tmp_path / "o"
    rec = {"format": "ssgwarp-demo/1", "options": {"size": "small", "seed": 0, "views": [4, 2]}, "stages": {}}
    write_json(out / "demo.json", {**rec, "stages": {"reconstruct": {"done": True}}})
    (out / "contact_sheet.png").write_text("old")
    with pytest.raises(InputError, match=r"other options .*seed 0 -> 3; size small -> default"):
        _prepare_out(out, force=False, resume=True, record={**rec, "options": {**rec["options"], "seed": 3,
                                                                               "size": "default"}})
    assert _prepare_out(out, force=False, resume=True, record=dict(rec))["stages"] == {"reconstruct": {"done": True}}


def test_force_removes_only_what_the_demo_writes(tmp_path):
    from ssgwarp.demo import _prepare_out
    from ssgwarp.errors import InputError, SsgwarpError

    out = tmp_path / "o"
    (out / "scene").mkdir(parents=True)
    (out / "scene" / "scene.ply").write_text("old")
    (out / "contact_sheet.png").write_text("old")
    (out / "notes.txt").write_text("mine")
    rec = {"format": "ssgwarp-demo/1", "options": {"size": "small"}, "stages": {}}
    with pytest.raises(SsgwarpError, match="already holds a demo run"):
        _prepare_out(out, force=False, resume=False, record=dict(rec))
    with pytest.raises(InputError, match="nothing to resume"):
        _prepare_out(out, force=False, resume=True, record=dict(rec))
    with pytest.raises(InputError, match="exclude each other"):
        _prepare_out(out, force=True, resume=True, record=dict(rec))
    _prepare_out(out, force=True, resume=False, record=dict(rec))
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


@pytest.mark.slow  # runs the small demo, interrupted and resumed, and its Stage 2 once more (~40 s)
def test_ctrl_c_in_a_demo_stage_resumes_to_the_uninterrupted_result(tmp_path, monkeypatch, fail_on_call):
    """Ctrl-C during Stage 2: exit 130, finished stages kept; --resume gives the same stylized scene as an
    uninterrupted Stage 2 on the same reconstruction (a copy of the run with the stylize stage undone)."""
    import shutil

    import ssgwarp.stylization.stage2 as st   # where optimise calls it
    from ssgwarp.formats.ply import read_ply

    _no_weights(monkeypatch)
    orig = fail_on_call(st, "backward_views", 7, "interrupt")
    out = tmp_path / "demo"
    argv = ["demo", "--out", out, "--size", "small", "--quiet", "--device", "cpu"]
    code, _, stderr = _main(argv)
    assert code == 130 and "interrupted" in stderr and "--resume" in stderr
    stages = json.loads((out / "demo.json").read_text())["stages"]
    assert set(stages) == {"data", "reconstruct", "group"}           # the finished stages are recorded
    assert torch.load(out / "stylized" / "stage2.ckpt", weights_only=False)["step"] == 6
    assert not (out / "summary.json").exists() and not (out / "stylized" / "scene.ply").exists()
    monkeypatch.setattr(st, "backward_views", orig)
    # the reference: the same run, its interrupted Stage 2 removed, run uninterrupted
    ref = tmp_path / "ref"
    shutil.copytree(out, ref)
    shutil.rmtree(ref / "stylized")
    code, stdout, stderr = _main(argv + ["--resume"])
    assert code == 0, stderr
    code, _, stderr = _main(["demo", "--out", ref, "--size", "small", "--quiet", "--device", "cpu", "--resume"])
    assert code == 0, stderr
    a, b = read_ply(ref / "stylized" / "scene.ply"), read_ply(out / "stylized" / "scene.ply")
    for k, v in a.tensors().items():
        assert torch.equal(v, b.tensors()[k]), k


# ----------------------------------------------------------------------------- the procedural scene
def test_transforms_capture_reads_back_with_the_cameras_it_was_rendered_from(tmp_path):
    """OpenGL axes in transforms.json: the loader recovers the ring (OpenCV) and re-rendering the
    ground truth from the loaded cameras reproduces the written images to 8-bit precision."""
    from ssgwarp.capture.datasets import load_dataset

    gt = P.build_scene(0.3)
    cams = P.ring_cameras(4, 40, 30)
    images, objects = P.render_views(gt, cams)
    path = P.write_transforms_dataset(tmp_path / "cap", images, cams)
    meta = json.loads(path.read_text())
    c2w_gl = torch.tensor(meta["frames"][1]["transform_matrix"], dtype=torch.float64)
    # OpenGL: the camera looks down its -z axis, towards the ring's target
    to_target = torch.tensor([0.0, 0.0, 0.35], dtype=torch.float64) - c2w_gl[:3, 3]
    assert float(torch.nn.functional.cosine_similarity(-c2w_gl[:3, 2], to_target, dim=0)) > 0.999
    data = load_dataset(tmp_path / "cap", split_every=0)
    assert torch.allclose(data.cameras.viewmats, cams.viewmats, atol=1e-5)
    assert torch.allclose(data.cameras.Ks, cams.Ks, atol=1e-5)
    again, _ = P.render_views(gt, data.cameras)
    assert float((again - data.images).abs().max()) <= 0.5 / 255 + 1e-4
    # every view sees all five objects
    for v in range(4):
        assert set(objects[v].unique().tolist()) >= {0, 1, 2, 3, 4}


def test_procedural_scene_and_style_image():
    gt = P.build_scene(1.0)
    counts = gt.counts()
    assert list(counts) == list(P.OBJECT_NAMES) and min(counts.values()) > 100
    assert gt.scene.sh_degree == 0 and gt.scene.identities is None        # only what the scene needs
    assert len(P.build_scene(0.25)) < 0.4 * len(gt)
    s0, s0b, s1 = P.style_image(64, 48, seed=0), P.style_image(64, 48, seed=0), P.style_image(64, 48, seed=1)
    assert s0.shape == (48, 64, 3) and s0.dtype == np.float32 and np.array_equal(s0, s0b)
    assert not np.array_equal(s0, s1) and 0.0 <= s0.min() and s0.max() <= 1.0
    sat = s0.max(axis=2) - s0.min(axis=2)
    assert (sat > 0.5).mean() > 0.2                                   # bold, saturated colour
    assert len(np.unique((s0 * 255).astype(np.uint8).reshape(-1, 3), axis=0)) >= 5


def test_group_agreement_scores():
    from ssgwarp.demo import group_agreement

    objects = torch.tensor([[[-1, 0, 0, 1], [2, 2, 1, 1]]])         # background, objects 0, 1, 2
    same = torch.tensor([[[5, 0, 0, 1], [2, 2, 1, 1]]])
    r = group_agreement(same, objects, 3)
    assert r["purity"] == 1.0 and r["separated"] == 3 and r["objects"] == 3 and r["pixels"] == 7
    merged = torch.tensor([[[5, 0, 0, 0], [2, 2, 0, 0]]])             # object 1 folded into object 0's group
    r = group_agreement(merged, objects, 3)
    assert r["separated"] == 1 and math.isclose(r["purity"], 5 / 7)
