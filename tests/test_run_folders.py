"""Every kind of run folder where a command takes one: a stylized run (``ssgwarp stylize``'s output)
resolves its source reconstruction's cameras, split and groups through :class:`ssgwarp.services.runs.Run`,
and ``render`` renders it along those cameras on its own recorded background."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from ssgwarp.cli import main
from ssgwarp.core.fileio import read_image, write_json
from ssgwarp.formats.ply import write_ply
from ssgwarp.errors import InputError
from ssgwarp.services.runs import Run

from test_services import _recon_run, _scene

STYLED_BG = [0.1, 0.6, 0.2]


def write_classifier(run_dir, dim: int, groups: int) -> None:
    """A group classifier ``groups/classifier.pt`` of ``dim`` identity channels onto ``groups`` groups."""
    lin = torch.nn.Linear(dim, groups)
    (run_dir / "groups").mkdir()
    torch.save({"format": 1, "dim": dim, "num_groups": groups,
                "state_dict": {k: v.detach() for k, v in lin.state_dict().items()}}, run_dir / "groups" / "classifier.pt")


def stylized_run(tmp_path, *, grouped: bool = True, keyviews: bool = True):
    """A reconstruction (3 cameras, v1 held out; grouped: 8 identity channels, 3 groups) and a stylized run
    of it as ``ssgwarp stylize`` writes one (scene.ply, metrics.json naming source_scene, keyviews/)."""
    rec = _recon_run(tmp_path / "rec")
    if grouped:
        write_ply(rec / "scene.ply", _scene(ids=8))
        write_classifier(rec, 8, 3)
    sty = tmp_path / "sty"
    sty.mkdir()
    styled = _scene(seed=4, ids=8 if grouped else 0)
    write_ply(sty / "scene.ply", styled)
    write_json(sty / "metrics.json", {"source_scene": str(rec.resolve()), "style": "style.png", "mode": "ist",
                                      "background": STYLED_BG})
    if keyviews:
        (sty / "keyviews").mkdir()
        write_json(sty / "keyviews" / "keyviews.json", {"ids": [0, 2], "names": ["v0.png", "v2.png"]})
    return rec, sty


def test_a_stylized_run_finds_its_sources_groups_and_its_own_key_views(tmp_path):
    rec, sty = stylized_run(tmp_path)
    s = Run.open(sty)
    assert s.kind == "stylized" and s.camera_dir == rec.resolve()
    assert s.groups_dir == rec.resolve() / "groups" and s.keyviews_dir == sty / "keyviews"
    r = Run.open(rec)
    assert r.groups_dir == rec / "groups" and r.keyviews_dir is None
    # a stylized run grouped itself: its own groups win
    write_classifier(sty, 8, 2)
    assert Run.open(sty).groups_dir == sty / "groups"


def test_runs_never_grouped_have_no_groups(tmp_path):
    rec, sty = stylized_run(tmp_path, grouped=False, keyviews=False)
    assert Run.open(rec).groups_dir is None and Run.open(sty).groups_dir is None
    assert Run.open(sty).keyviews_dir is None
    (sty / "keyviews").mkdir()                   # a folder without keyviews.json is not a key-view record
    assert Run.open(sty).keyviews_dir is None


def test_render_takes_a_stylized_run_along_its_sources_cameras(tmp_path, capsys):
    rec, sty = stylized_run(tmp_path, grouped=False)
    out = tmp_path / "frames"
    assert main(["render", str(sty), "--out", str(out), "--path", "4", "--quiet"]) == 0, capsys.readouterr().err
    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == 4 and (out / "path_cameras.json").is_file()
    img = read_image(frames[0], 3)
    assert img.shape == (16, 20, 3)
    # the stylized run's recorded background where nothing is drawn (corners of the frame)
    assert np.allclose(img[0, 0], STYLED_BG, atol=0.02)
    out2 = tmp_path / "test_views"
    assert main(["render", str(sty), "--out", str(out2), "--split", "test", "--quiet"]) == 0
    assert [p.name for p in out2.glob("*.png")] == ["v1.png"]
    # the stylized scene, not its source's: the renders differ
    out3 = tmp_path / "source_views"
    assert main(["render", str(rec), "--out", str(out3), "--split", "test", "--quiet"]) == 0
    assert not np.allclose(read_image(out3 / "v1.png", 3), read_image(out2 / "v1.png", 3), atol=0.05)


def test_render_of_a_stylized_run_whose_source_moved_is_one_clear_error(tmp_path, capsys):
    rec, sty = stylized_run(tmp_path, grouped=False)
    rec.rename(tmp_path / "moved")
    assert main(["render", str(sty), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "source_scene" in err and "cameras.json" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    with pytest.raises(InputError, match="run folder not found"):
        Run.open(tmp_path / "nothing")


def test_a_command_that_needs_a_reconstruction_names_a_stylized_runs_source(tmp_path):
    rec, sty = stylized_run(tmp_path, grouped=False)
    with pytest.raises(InputError, match=f"a stylize output, not a reconstruction run; .* source reconstruction {rec}"):
        Run.reconstruction(sty)
    assert Run.reconstruction(rec).kind == "reconstruction"


def test_one_write_sequence_makes_a_run_the_readers_take(tmp_path):
    """write_run (reconstruct's and import's) and write_orbit_run write a folder Run and load_run read back;
    update_metrics adds entries and keeps the others; metrics.json is written last, only when given."""
    from ssgwarp.core.fileio import read_json
    from ssgwarp.services.runs import RUN_FILES, load_run, update_metrics, write_orbit_run, write_run

    rec = Run.open(_recon_run(tmp_path / "rec"))
    _, data = rec.load(load_images=False)
    seen = []
    write_run(tmp_path / "out", _scene(seed=2), data, {"psnr": 20.0}, record={"seed": 3},
              finish=lambda: seen.append(sorted(p.name for p in (tmp_path / "out").iterdir())) or {"extra": 1})
    assert seen == [["cameras.json", "data.json", "scene.ply"]]        # finish: before metrics.json
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(RUN_FILES)
    assert read_json(tmp_path / "out" / "metrics.json") == {"psnr": 20.0, "extra": 1}
    assert read_json(tmp_path / "out" / "data.json")["seed"] == 3
    scene, back = load_run(tmp_path / "out", load_images=False)
    assert len(scene) == 30 and back.train_ids == [0, 2] and back.test_ids == [1]
    orbit = write_orbit_run(_scene(n=200), tmp_path / "orbit", source=tmp_path / "x.ply", views=4, width=24)
    r = Run.reconstruction(tmp_path / "orbit")
    assert not (tmp_path / "orbit" / "metrics.json").exists()
    assert len(r.cameras) == 4 and r.train_ids == [0, 1, 2, 3] and r.test_ids == []
    assert r.data["orbit"]["cameras"] == orbit["cameras"]
    assert update_metrics(tmp_path / "out", {"psnr": 21.0})["extra"] == 1
    assert read_json(tmp_path / "out" / "metrics.json") == {"psnr": 21.0, "extra": 1}


def test_a_commands_own_out_folder_is_claimed_by_the_one_policy(tmp_path):
    """claim_folder: an empty or absent folder is taken; a non-empty one is refused in one line naming its first
    files unless force, which empties it; a file there is refused unless force."""
    from ssgwarp.errors import SsgwarpError
    from ssgwarp.services.runs import claim_folder

    out = tmp_path / "frames"
    assert claim_folder(out, force=False).is_dir()
    for i in range(5):
        (out / f"{i:03d}.png").write_bytes(b"x")
    with pytest.raises(SsgwarpError, match=r"already holds files \(000.png, 001.png, 002.png, ...\); pass --force"):
        claim_folder(out, force=False)
    assert len(list(out.iterdir())) == 5
    claim_folder(out, force=True)
    assert out.is_dir() and not any(out.iterdir())
    f = tmp_path / "file"
    f.write_bytes(b"x")
    with pytest.raises(InputError, match="not a folder; pass --force"):
        claim_folder(f, force=False)
    assert claim_folder(f, force=True).is_dir()


def test_a_stage_record_resumes_its_finished_stages_with_the_same_options_only(tmp_path):
    """resumed_stages (stylize's run.json, the demo's demo.json): the finished stages on --resume with the same
    record; other options refused naming them; a file that is not the record refused; none: {} or, required,
    'nothing to resume'."""
    from ssgwarp.services.runs import claim, resume_record, resumed_stages

    out = tmp_path / "out"
    out.mkdir()
    (out / "scene.ply").write_bytes(b"x")
    rec = resume_record(**{"--seed": 1})
    c = claim(out, ["scene.ply", "run.json"], resume=True)
    assert resumed_stages(c, "run.json", "signature", rec, "the earlier run", kind="a stylize record") == {}
    with pytest.raises(InputError, match="nothing to resume"):
        resumed_stages(c, "run.json", "signature", rec, "the earlier run", kind="x", required=True)
    write_json(out / "run.json", {"signature": rec, "stages": {"stage2": True}})
    c = claim(out, ["scene.ply", "run.json"], resume=True)
    assert resumed_stages(c, "run.json", "signature", rec, "the earlier run", kind="x") == {"stage2": True}
    with pytest.raises(InputError, match=r"--seed 1 -> 2"):
        resumed_stages(c, "run.json", "signature", resume_record(**{"--seed": 2}), "the earlier run", kind="x")
    with pytest.raises(InputError, match="not a demo record"):
        resumed_stages(c, "run.json", "signature", rec, "the earlier run", kind="a demo record", fmt="demo/1")
    fresh = claim(out, ["scene.ply"], force=True)
    assert resumed_stages(fresh, "run.json", "signature", resume_record(**{"--seed": 2}), "x", kind="x") == {}
