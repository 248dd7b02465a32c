"""``--config`` precedence: a flag on the command line beats the config file, which beats the
option's default (the stage's ``run`` is replaced by one that records the parsed arguments)."""
from __future__ import annotations

import json

import pytest

import ssgwarp.commands.render
from ssgwarp.cli import main


@pytest.fixture
def parsed(monkeypatch):
    seen = {}

    def fake_run(args):
        seen.update(vars(args))
        return 0

    monkeypatch.setattr(ssgwarp.commands.render, "run", fake_run)
    return seen


def test_flag_beats_config_beats_default(tmp_path, parsed):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"split": "test", "path": 7, "seed": 11, "no-progress": True}))
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--device", "cpu",
                 "--config", str(cfg), "--split", "train"]) == 0
    assert parsed["split"] == "train"          # the flag wins over the config's "test"
    assert parsed["path"] == 7                 # the config wins over the default (None)
    assert parsed["seed"] == 11                # also for the common options
    assert parsed["quiet"] is True             # keys may be spelled with dashes, and as any of a flag's names
    assert parsed["open"] is False             # neither: the default
    parsed.clear()
    # the flag placed before --config wins as well
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--seed", "3", "--device", "cpu",
                 "--config", str(cfg)]) == 0
    assert parsed["seed"] == 3 and parsed["split"] == "test"
    parsed.clear()
    # without --config: the defaults
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--device", "cpu"]) == 0
    assert parsed["split"] == "all" and parsed["path"] is None and parsed["seed"] == 0


@pytest.mark.parametrize("cfg, message", [
    ({"path": "seven"}, "'path' takes a whole number"),
    ({"split": "sideways"}, "'split' must be one of"),
    ({"quiet": "yes"}, "'quiet' is a switch: true or false"),
    ({"path": [1, 2]}, "'path' takes a whole number"),
    ({"weights": ["vgg16"]}, "'weights' must map model names to paths"),
])
def test_config_values_of_the_wrong_type_are_one_line(tmp_path, parsed, capsys, cfg, message):
    """(issue 60: a --config value went to the command as it was, e.g. a list where a number belongs.)"""
    path = tmp_path / "cfg.json"
    path.write_text(json.dumps(cfg))
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--device", "cpu",
                 "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err and str(path) in err, err
    assert not parsed


def test_config_not_utf8_is_one_line(tmp_path, parsed, capsys):
    path = tmp_path / "cfg.json"
    path.write_bytes(b'{"path": "\xff"}')
    assert main(["render", str(tmp_path / "run"), "--out", str(tmp_path / "o"), "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "not UTF-8" in err and "--config" in err and len(err.splitlines()) == 1, err


def test_reconstruct_options_and_config_keys_build_the_strategy_and_the_recipe(tmp_path, monkeypatch):
    """`reconstruct`'s --strategy / --max-gaussians / --sh-degree / --coarse-to-fine / --batch-scaling, from the
    command line or a --config file as before, land on the strategy dataclass and the Recipe of the config."""
    import ssgwarp.commands.reconstruct as command
    from ssgwarp.reconstruction.recipe import Recipe
    from ssgwarp.reconstruction.strategy import DefaultStrategy, MCMCStrategy

    seen = []

    def fake_reconstruct(data_dir, out, config, **kw):
        seen.append(config)
        return {"psnr": None, "ssim": None, "num_gaussians": 0, "train_seconds": 0.0, "iters": 1}

    monkeypatch.setattr(command, "reconstruct", fake_reconstruct)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"strategy": "mcmc", "max-gaussians": 500, "sh_degree": 1, "coarse-to-fine": 2,
                               "batch-scaling": "linear"}))
    base = ["reconstruct", str(tmp_path / "cap"), "--out", str(tmp_path / "run"), "--device", "cpu"]
    assert main(base + ["--config", str(cfg), "--sh-degree", "2"]) == 0
    assert main(base) == 0
    with_config, plain = seen
    assert with_config.strategy == MCMCStrategy(max_gaussians=500)
    assert with_config.recipe == Recipe(sh_degree=2, res_start=2.0, batch_scaling="linear")   # (the flag wins)
    assert plain.strategy == DefaultStrategy() and plain.recipe == Recipe()
