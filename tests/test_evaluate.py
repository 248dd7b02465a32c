"""``ssgwarp evaluate`` on small run folders built here: a reconstruction and a stylize output."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from ssgwarp.core.cameras import Cameras
from ssgwarp.raster.scene import GaussianScene

W, H, F_PX = 32, 24, 40.0


def _scene() -> GaussianScene:
    """Flat Gaussians tiling the plane z = 4 (smooth colours) and a small blob in front at z = 3."""
    g = torch.linspace(-2.6, 2.6, 36)
    gy, gx = torch.meshgrid(g * 0.75, g, indexing="ij")
    plane = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((gx.numel(),), 4.0)], -1)
    rgb = torch.stack([0.5 + 0.15 * plane[:, 0], 0.5 - 0.1 * plane[:, 1], torch.full((len(plane),), 0.3)], -1)
    s = GaussianScene.from_points(plane, rgb.clamp(0, 1), opacity=0.99, scale=torch.full((len(plane),), 0.11))
    s = s.replace(log_scales=s.log_scales.clone().index_fill_(1, torch.tensor([2]), math.log(1e-4)))
    gen = torch.Generator().manual_seed(0)
    blob = torch.randn(40, 3, generator=gen) * 0.08 + torch.tensor([0.0, 0.0, 3.0])
    b = GaussianScene.from_points(blob, torch.tensor([0.9, 0.2, 0.2]).expand(40, 3).clone(), opacity=0.9,
                                  scale=torch.full((40,), 0.07))
    return GaussianScene(*(torch.cat([x, y]) for x, y in zip(
        (s.means, s.log_scales, s.quats, s.logit_opacities, s.sh_dc),
        (b.means, b.log_scales, b.quats, b.logit_opacities, b.sh_dc))))


def _cameras(n: int = 6) -> Cameras:
    vms = torch.eye(4).repeat(n, 1, 1)
    vms[:, 0, 3] = -(torch.arange(n, dtype=torch.float32) * 0.12 - 0.3)     # cameras along +x, looking at +z
    K = torch.tensor([[F_PX, 0.0, W / 2], [0.0, F_PX, H / 2], [0.0, 0.0, 1.0]])
    return Cameras(vms, K.expand(n, 3, 3).clone(), W, H, [f"v{i}.png" for i in range(n)])


@pytest.fixture
def runs(tmp_path, monkeypatch):
    """(reconstruction dir, stylized dir, style image) built with the project's own writers."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.services.runs import data_json
    from ssgwarp.core.fileio import write_image, write_json
    from ssgwarp.formats.ply import write_ply

    for var in ("SSGWARP_WEIGHTS", "SSGWARP_RAFT", "SSGWARP_LPIPS", "SSGWARP_VGG16"):
        monkeypatch.delenv(var, raising=False)
    scene, cams = _scene(), _cameras()
    cap = tmp_path / "capture"
    with torch.no_grad():
        colors, alphas, _ = scene.render(cams)
    imgs = colors + (1 - alphas)                   # white background
    frames = []
    gl = np.diag([1.0, -1.0, -1.0, 1.0])
    for i, name in enumerate(cams.names):
        write_image(cap / "images" / name, imgs[i].clamp(0, 1))
        frames.append({"file_path": f"images/{name}", "transform_matrix": (cams.camtoworlds[i].double().numpy() @ gl).tolist()})
    write_json(cap / "transforms.json", {"fl_x": F_PX, "fl_y": F_PX, "cx": W / 2, "cy": H / 2, "w": W, "h": H,
                                         "frames": frames})
    data = load_dataset(cap, split_every=3)
    assert torch.allclose(data.cameras.viewmats, cams.viewmats, atol=1e-5)
    recon = tmp_path / "runs" / "recon"
    write_ply(recon / "scene.ply", scene)
    data.cameras.save(recon / "cameras.json")
    write_json(recon / "data.json", data_json(data))
    write_json(recon / "metrics.json", {"iters": 0, "note": "kept"})

    # a 'stylized' run: recoloured, with strong view-dependent (SH degree 1) colour = view-inconsistent
    gen = torch.Generator().manual_seed(1)
    styled = scene.with_sh_degree(1)
    styled = styled.replace(sh_dc=styled.sh_dc * 0.5 + 0.3, sh_rest=torch.randn(styled.sh_rest.shape, generator=gen) * 1.5)
    sty = tmp_path / "runs" / "styled"
    write_ply(sty / "scene.ply", styled)
    yy, xx = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    checker = np.where(((yy // 4 + xx // 4) % 2 == 0)[..., None], [0.9, 0.8, 0.1], [0.1, 0.2, 0.7]).astype(np.float32)
    write_image(tmp_path / "style.png", checker)
    write_json(sty / "metrics.json", {"source_scene": str(recon.resolve()), "style": str(tmp_path / "style.png"),
                                      "mode": "global", "gram_style_loss": 1.25})
    return recon, sty, tmp_path / "style.png"


def test_evaluate_cli_writes_metrics_pairs_and_table(runs, tmp_path, capsys):
    from ssgwarp.cli import main

    recon, sty, _ = runs
    table = tmp_path / "table.md"
    rc = main(["evaluate", str(recon), str(sty), "--max-pairs", "2", "--gap", "3", "--device", "cpu",
               "--table", str(table), "--views", "all"])
    assert rc == 0, capsys.readouterr().err
    m_rec = json.loads((recon / "metrics.json").read_text())
    m_sty = json.loads((sty / "metrics.json").read_text())
    # other keys of metrics.json are kept
    assert m_rec["note"] == "kept" and m_sty["gram_style_loss"] == 1.25 and m_sty["mode"] == "global"
    er, es = m_rec["evaluation"], m_sty["evaluation"]
    assert er["kind"] == "reconstruction" and es["kind"] == "stylized" and es["mode"] == "global"
    assert er["views"] == 6 and er["resolution"] == [W, H] and er["view_split"] == "all"
    assert er["views_scored"] == "6 all captured views (training and held out)"
    c = er["consistency"]["reprojection"]
    assert c["short"]["pairs"] == 2 and c["long"]["pairs"] == 2 and c["long"]["gap"] == 3
    assert c["short"]["coverage"] > 0.5
    # a diffuse scene is consistent; strong view-dependent colour is measurably not
    assert c["short"]["rmse"] < 0.03 and c["long"]["rmse"] < 0.03
    cs = es["consistency"]["reprojection"]
    assert cs["short"]["rmse"] > 2 * c["short"]["rmse"] and cs["long"]["rmse"] > cs["short"]["rmse"]
    # reconstruction quality against the captured images (8-bit PNGs of the same renders)
    q = er["quality"]
    assert q["split"] == "test" and q["views"] == 2 and q["psnr"] > 40 and q["ssim"] > 0.99
    # style / content: extractor always reported; stylized run has both losses
    assert es["style_content"]["extractor"].startswith("random-multiscale")
    assert es["style_content"]["gram_style_loss"] > 0 and es["style_content"]["content_loss"] > 0
    # the weight-free distances, for the stylized renders and for the source renders of the same views
    for k in ("color", "texture"):
        assert es["style_content"][f"style_distance_{k}"] > 0 and es["style_content"][f"style_distance_{k}_original"] > 0
    assert "gram_style_loss" not in er.get("style_content", {})       # no style image for the reconstruction
    assert "no local lpips weights" in er["skipped"]["lpips"] and "ssgwarp weights --download lpips" in \
        er["skipped"]["lpips"]
    assert "raft" in er["skipped"]["flow warp"]
    # inspection images: a strip and a mask per saved pair
    strips = sorted(p.name for p in (recon / "evaluation" / "pairs").glob("*.png"))
    assert len(strips) == 8 and "short_reprojection_v0-v1.png" in strips and "short_reprojection_v0-v1_mask.png" in strips
    text = table.read_text()
    assert "| metric | recon | styled |" in text and "short-range RMSE (reprojection)" in text
    assert "PSNR" in text and "Gram style loss" in text and "colour distance (SW, Lab)" in text


def test_evaluate_scores_novel_path_views_by_default(runs, tmp_path):
    """The default is the papers' protocol: novel views on a smooth path, none of them a training view;
    metrics say which views were scored; --views test scores the held-out views."""
    from ssgwarp.core.cameras import Cameras
    from ssgwarp.evaluation.evaluate import EvalOptions, evaluate_run

    recon, sty, style = runs
    assert EvalOptions().views == "path"
    res = evaluate_run(sty, EvalOptions(max_pairs=2, gap=3, path_frames=12, save_pairs=0), write=False)
    assert res["view_split"] == "path" and res["views"] == 12
    assert res["views_scored"] == "12 novel views on a smooth path through the 4 training cameras"
    assert res["consistency"]["reprojection"]["short"]["pairs"] == 2
    assert res["style_content"]["style_distance_color"] > 0
    # no path frame coincides with a training camera
    train = Cameras.load(recon / "cameras.json")
    from ssgwarp.evaluation.evaluate import scored_cameras
    from ssgwarp.services.runs import load_run

    _, data = load_run(recon, load_images=False)
    path, ids, _ = scored_cameras(data.cameras, data.train_ids, data.test_ids, EvalOptions(path_frames=12))
    assert ids is None and len(path) == 12
    d = torch.cdist(path.centers.double(), train.centers.double())
    assert float(d.min()) > 1e-3
    test = evaluate_run(recon, EvalOptions(views="test", max_pairs=1, save_pairs=0), write=False)
    assert test["view_split"] == "test" and test["views"] == 2 and "held-out" in test["views_scored"]


def test_evaluate_with_style_gives_lower_style_loss_to_matching_colours(runs, tmp_path):
    """The Gram loss ranks runs: a run recoloured towards the style's colours scores lower."""
    from ssgwarp.evaluation.evaluate import EvalOptions, evaluate_run
    from ssgwarp.evaluation.features import load_extractor
    from ssgwarp.formats.ply import read_ply, write_ply

    recon, sty, style = runs
    ext = load_extractor(None, "cpu")
    opts = EvalOptions(style=str(style), pairs=("short",), max_pairs=1, save_pairs=0)
    base = evaluate_run(recon, opts, extractor=ext, write=False)
    # recolour the scene as the style checker at the scale it is compared at (16 px style resized to the
    # renders' 24 px height: 6 px cells, 0.6 world units on the plane z = 4)
    s = read_ply(recon / "scene.ply")
    yellow = torch.tensor([0.9, 0.8, 0.1])
    blue = torch.tensor([0.1, 0.2, 0.7])
    cell = torch.floor(s.means[:, 0] / 0.6) + torch.floor(s.means[:, 1] / 0.6)
    target = torch.where((cell % 2 == 0)[:, None], yellow, blue)
    from ssgwarp.raster.scene import rgb_to_sh_dc

    s2 = s.replace(sh_dc=rgb_to_sh_dc(target))
    closer = tmp_path / "runs" / "closer"
    closer.mkdir()
    for f in ("cameras.json", "data.json"):
        (closer / f).write_text((recon / f).read_text())
    write_ply(closer / "scene.ply", s2)
    res = evaluate_run(closer, opts, extractor=ext, write=False)
    assert res["style_content"]["style_image"] == str(style)
    assert res["style_content"]["gram_style_loss"] < base["style_content"]["gram_style_loss"]
    assert not (closer / "metrics.json").exists()


def test_evaluate_bad_inputs_are_one_line_errors(runs, tmp_path, capsys):
    from ssgwarp.cli import main

    recon, sty, _ = runs
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["evaluate", str(empty), "--device", "cpu"]) == 2
    assert "no scene.ply" in capsys.readouterr().err
    assert main(["evaluate", str(recon), "--pairs", "medium", "--device", "cpu"]) == 2
    assert "--pairs" in capsys.readouterr().err
    assert main(["evaluate", str(recon), "--warp", "flow", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "raft" in err and err.count("\n") == 1
    (sty / "metrics.json").write_text(json.dumps({"source_scene": str(tmp_path / "moved")}))
    assert main(["evaluate", str(sty), "--device", "cpu"]) == 2
    assert "source_scene" in capsys.readouterr().err
    assert "evaluation" not in json.loads((recon / "metrics.json").read_text())   # nothing written on errors


# ----------------------------------------------------------------------------- one definition per metric
def test_evaluate_reproduces_the_numbers_stylize_reports(tmp_path, capsys):
    """`stylize` reports style / content numbers on its training views with its own extractor (here the weight-free
    random-edges one, not evaluate's default); `evaluate --views train` on its output computes them with the same
    function (metrics.style_scores) on the same views and the run's extractor: the same numbers. Both say which
    views. Without Stage 1 weights the groups take regions of the style image (stylize says so); where they go
    unused (finetune without Stage 1) stylize says that in one line."""
    from test_stylize import _write_run

    from ssgwarp.cli import main

    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--iters", "3", "--keyviews", "2",
                 "--max-side", "48", "--path-frames", "0", "--device", "cpu"]) == 0
    said = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    # without Stage 1 each group is matched against its own region of the style image (the groups are used)
    assert m["extractor"].endswith(",edges") and m["groups"] == 3 and m["groups_used"] is True
    assert "each of the 3 groups against its own region" in said and "groups are not used" not in said
    assert f"on the {m['views']} training views ({m['extractor']})" in said
    assert main(["stylize", str(run), "--style", str(style), "--out", str(tmp_path / "ft"), "--iters", "2",
                 "--keyviews", "2", "--max-side", "48", "--path-frames", "0", "--mode", "finetune",
                 "--device", "cpu"]) == 0
    unused = [ln for ln in capsys.readouterr().out.splitlines() if "groups are not used" in ln]
    assert len(unused) == 1 and "3 groups" in unused[0] and "ssgwarp weights --download stage1" in unused[0]
    assert json.loads((tmp_path / "ft" / "metrics.json").read_text())["groups_used"] is False
    assert main(["evaluate", str(out), "--views", "train", "--max-pairs", "1", "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    sc = json.loads((out / "metrics.json").read_text())["evaluation"]["style_content"]
    assert sc["extractor"] == m["extractor"] and sc["views"] == f"{m['views']} training views"
    assert f"on {m['views']} training views, {m['extractor']}: Gram style loss" in printed
    pairs = [("gram_style_loss", m["gram_style_loss"]), ("gram_style_loss_original", m["gram_style_loss_original"]),
             ("content_loss", m["content_loss"])]
    pairs += [(f"style_distance_{k}{s}", m["style_distance" + s][k]) for k in ("color", "texture")
              for s in ("", "_original")]
    for key, want in pairs:
        assert sc[key] == pytest.approx(want, rel=1e-4, abs=1e-7), key
    # the default (novel path views) differs, and says so beside the numbers
    assert main(["evaluate", str(out), "--max-pairs", "1", "--path-frames", "4", "--device", "cpu", "--force"]) == 0
    sc2 = json.loads((out / "metrics.json").read_text())["evaluation"]["style_content"]
    assert sc2["views"].startswith("4 novel views") and sc2["gram_style_loss"] != pytest.approx(sc["gram_style_loss"])


def test_style_scores_extractor_names_round_trip():
    from ssgwarp.errors import InputError, WeightsNotFound
    from ssgwarp.evaluation.metrics import extractor_from_name
    from ssgwarp.evaluation.features import PyramidPatches, RandomMultiScale, RandomStrokes

    made = [RandomMultiScale(**kw) for kw in ({}, {"seed": 3, "channels": 64, "stride": 4},
                                              {"edges": True, "scales": (2, 4, 8)})]
    made += [RandomStrokes(seed=2, channels=8, scales=(2,), dilations=(1, 2)), PyramidPatches(3, (1, 2))]
    for ext in made:
        again = extractor_from_name(ext.name)
        x = torch.rand(1, 3, 16, 16)
        assert again.name == ext.name and all(torch.equal(a, b) for a, b in zip(again(x), ext(x)))
    for bad in ("random-multiscale:seed0,zz", "resnet:1", "random-multiscale:seedx", "patches:p3", "random-strokes:x"):
        with pytest.raises(InputError):
            extractor_from_name(bad)
    with pytest.raises(WeightsNotFound):
        extractor_from_name("vgg16:relu3_1")


# ----------------------------------------------------------------------------- --force
def test_evaluate_reproduces_stylize_with_the_patch_features(tmp_path, capsys):
    """stylize --extractor patches records the extractor's name; evaluate rebuilds that extractor from the name
    and gives the same Gram and content numbers on the same views (no note about a different extractor)."""
    from test_stylize import _write_run

    from ssgwarp.cli import main

    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--iters", "3", "--mode", "global",
                 "--extractor", "patches", "--path-frames", "0", "--device", "cpu"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["extractor"] == "patches:p5s1-2-4" and m["mode"] == "global"
    assert m["config"]["content_weight"] == 0.01        # the patch features' own default, recorded resolved
    assert main(["evaluate", str(out), "--views", "train", "--max-pairs", "1", "--device", "cpu"]) == 0
    sc = json.loads((out / "metrics.json").read_text())["evaluation"]["style_content"]
    assert sc["extractor"] == m["extractor"] and "differ" not in capsys.readouterr().out
    for key in ("gram_style_loss", "gram_style_loss_original", "content_loss"):
        assert sc[key] == pytest.approx(m[key], rel=1e-4, abs=1e-7), key


def test_evaluate_refuses_to_overwrite_an_evaluation_without_force(runs, tmp_path, capsys):
    from ssgwarp.cli import main

    recon, sty, _ = runs
    args = ["evaluate", str(recon), "--max-pairs", "1", "--path-frames", "3", "--device", "cpu", "--save-pairs", "0"]
    assert main(args) == 0
    first = json.loads((recon / "metrics.json").read_text())["evaluation"]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds an evaluation" in err[0] and "--force" in err[0]
    assert json.loads((recon / "metrics.json").read_text())["evaluation"] == first     # untouched
    # an evaluation/ folder alone (metrics.json without the entry) counts too
    m = json.loads((recon / "metrics.json").read_text())
    del m["evaluation"]
    (recon / "metrics.json").write_text(json.dumps(m))
    assert main(args) == 2 and "already holds an evaluation (evaluation)" in capsys.readouterr().err
    (recon / "evaluation" / "stale.png").write_bytes(b"x")
    assert main(args + ["--force"]) == 0
    assert not (recon / "evaluation" / "stale.png").exists()      # --force replaces the earlier evaluation
    assert "evaluation" in json.loads((recon / "metrics.json").read_text())
    # an existing --table file outside the runs is refused too, and replaced with --force
    table = tmp_path / "table.md"
    table.write_text("mine")
    assert main(["evaluate", str(sty), "--max-pairs", "1", "--path-frames", "3", "--device", "cpu",
                 "--table", str(table)]) == 2
    assert "--table" in capsys.readouterr().err and table.read_text() == "mine"
    assert "evaluation" not in json.loads((sty / "metrics.json").read_text())
    assert main(["evaluate", str(sty), "--max-pairs", "1", "--path-frames", "3", "--device", "cpu",
                 "--table", str(table), "--force"]) == 0
    assert table.read_text().startswith("Evaluation (")


def test_style_scores_score_the_renders_as_shown():
    """A colour transfer can push renders above 1: the numbers are those of the clamped images (as saved and as
    evaluate renders them), so stylize's unclamped renders and evaluate's clamped ones give the same numbers."""
    from ssgwarp.evaluation.metrics import style_scores
    from ssgwarp.evaluation.features import RandomMultiScale

    g = torch.Generator().manual_seed(0)
    ext = RandomMultiScale(seed=0).freeze()
    images, originals = torch.rand(2, 24, 32, 3, generator=g) * 1.8, torch.rand(2, 24, 32, 3, generator=g)
    style, alphas = torch.rand(20, 20, 3, generator=g), torch.ones(2, 24, 32)
    a = style_scores(ext, images, style, originals, alphas=alphas)
    b = style_scores(ext, images.clamp(0, 1), style, originals, alphas=alphas)
    assert a == b and set(a) == {"gram_style_loss", "gram_style_loss_original", "content_loss",
                                 "style_distance_color", "style_distance_texture",
                                 "style_distance_color_original", "style_distance_texture_original"}
    assert style_scores(None, images, None) == {} and "content_loss" not in style_scores(ext, images, style)
