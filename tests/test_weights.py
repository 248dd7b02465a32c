"""ssgwarp.services.weights: resolution order, the Hugging Face / torch hub caches in their real layouts, offline
behaviour, downloads (mocked at the libraries' boundary: never the network), corrupt files, `ssgwarp weights`,
and `ssgwarp stylize` running Stage 1 + Stage 2 from fake caches alone."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from fakeweights import (copy_tree, fake_hf_cache, fake_torch_hub, hf_cache_entry, random_stage1_components,
                         save_stage1, save_tiny_sam, vgg16_state)
from ssgwarp.services import weights as W
from ssgwarp.services.weight_specs import SPECS
from ssgwarp.cli import main
from ssgwarp.errors import InputError, WeightsNotFound

STAGE1 = ("sd15", "controlnet_depth", "ip_adapter", "image_encoder")


@pytest.fixture(scope="module")
def caches(tmp_path_factory):
    """A Hugging Face cache (tiny Stage 1 models + tiny SAM) and a torch hub folder (VGG16 conv1-conv3)."""
    pytest.importorskip("diffusers")
    root = tmp_path_factory.mktemp("fake-caches")
    saved = save_stage1(random_stage1_components("tiny", seed=0), root / "saved")
    sam = save_tiny_sam(root / "saved" / "sam")
    fake_hf_cache(root / "hf" / "hub", saved, sam=sam)
    fake_torch_hub(root / "torch", vgg=vgg16_state("relu3_3"))
    shutil.rmtree(root / "saved")           # only the caches remain
    return root


def use(monkeypatch, root: Path, online: bool = False) -> None:
    """Point HF_HOME / TORCH_HOME at ``root``; ``online``: downloads allowed (they must then be mocked)."""
    monkeypatch.setenv("HF_HOME", str(root / "hf"))
    monkeypatch.setenv("TORCH_HOME", str(root / "torch"))
    if online:
        for var in ("SSGWARP_OFFLINE", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
            monkeypatch.delenv(var, raising=False)


class FakeHub:
    """Stands in for huggingface_hub.snapshot_download / HfApi.model_info and torch.hub.download_url_to_file:
    records what they were asked for and writes the files in the real layouts (or fails, when told to)."""

    def __init__(self, monkeypatch, tmp_path, fail: BaseException | None = None):
        import huggingface_hub
        import torch.hub

        self.calls, self.fail, self.tmp = [], fail, tmp_path
        monkeypatch.setattr(huggingface_hub, "snapshot_download", self.snapshot_download)
        monkeypatch.setattr(huggingface_hub.HfApi, "model_info", self.model_info)
        monkeypatch.setattr(torch.hub, "download_url_to_file", self.download_url_to_file)
        monkeypatch.setattr(W, "_url_size", lambda url: 1234)
        self.probes = []           # the network probe: answered here, never by the network
        monkeypatch.setattr(W, "_connect", self.connect)

    def connect(self, host, port, timeout):
        self.probes.append(host)
        if isinstance(self.fail, OSError) and "probe" in str(self.fail):
            raise self.fail

    LISTINGS = {"h94/IP-Adapter": {"models/ip-adapter_sd15.safetensors": 44_642_768,
                                   "models/ip-adapter_sd15.bin": 44_700_000},
                # a repo without the fp32 safetensors: the .bin is fetched instead
                "lllyasviel/control_v11f1p_sd15_depth": {"config.json": 945, "diffusion_pytorch_model.bin": 1_445_157_124,
                                                         "diffusion_pytorch_model.fp16.safetensors": 722_000_000}}

    def model_info(self, repo_id, **kw):        # installed on HfApi as a bound method of this object
        from types import SimpleNamespace

        self.calls.append(("model_info", repo_id, kw))
        return SimpleNamespace(siblings=[SimpleNamespace(rfilename=f, size=n)
                                         for f, n in self.LISTINGS.get(repo_id, {}).items()])

    def snapshot_download(self, **kw):
        self.calls.append(("snapshot_download", kw))
        if self.fail is not None:
            raise self.fail
        src = self.tmp / "served"
        src.mkdir(exist_ok=True)
        files = {}
        for rel in (p for p in kw["allow_patterns"] if "*" not in p):
            (src / Path(rel).name).write_bytes(b"weights of " + rel.encode())
            files[rel] = src / Path(rel).name
        return str(hf_cache_entry(kw["cache_dir"], kw["repo_id"], files))

    def download_url_to_file(self, url, dst, hash_prefix=None, progress=True):
        self.calls.append(("download_url_to_file", url, dst, hash_prefix))
        if self.fail is not None:
            raise self.fail
        torch.save(vgg16_state("relu1_2"), dst)


# ----------------------------------------------------------------------------- finding
def test_resolution_order_explicit_config_env_weights_dir_then_cache(tmp_path, monkeypatch):
    ck = fake_torch_hub(tmp_path / "torch", vgg={"features.0.weight": torch.zeros(1)})
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    routes = {}
    for name in ("explicit", "config", "env", "wdir"):
        routes[name] = tmp_path / name / "vgg16.pth"
        routes[name].parent.mkdir()
        routes[name].write_bytes(b"x")
    monkeypatch.setenv("SSGWARP_VGG16", str(routes["env"]))
    monkeypatch.setenv("SSGWARP_WEIGHTS", str(tmp_path / "wdir"))
    cfg = {"vgg16": str(routes["config"])}
    assert W.locate("vgg16", routes["explicit"], cfg) == (routes["explicit"], "explicit")
    assert W.locate("vgg16", None, cfg) == (routes["config"], "config")
    assert W.locate("vgg16") == (routes["env"], "$SSGWARP_VGG16")
    monkeypatch.delenv("SSGWARP_VGG16")
    assert W.locate("vgg16") == (routes["wdir"], "$SSGWARP_WEIGHTS")
    monkeypatch.delenv("SSGWARP_WEIGHTS")
    assert W.locate("vgg16") == (ck / "vgg16-397923af.pth", "torch hub cache")
    # a route that points nowhere falls through; an explicit path that does not exist is never replaced
    monkeypatch.setenv("SSGWARP_VGG16", str(tmp_path / "nowhere.pth"))
    assert W.find("vgg16") == ck / "vgg16-397923af.pth"
    assert W.find("vgg16", tmp_path / "typo.pth") is None
    with pytest.raises(WeightsNotFound, match="typo.pth does not exist"):
        W.require("vgg16", tmp_path / "typo.pth")


def test_hugging_face_cache_layout_is_read_through_huggingface_hub(caches, tmp_path, monkeypatch):
    use(monkeypatch, caches)
    snap = caches / "hf" / "hub" / "models--h94--IP-Adapter" / "snapshots" / "0123456789abcdef0123456789abcdef01234567"
    assert W.locate("image_encoder") == (snap / "models" / "image_encoder", "Hugging Face cache")
    assert W.find("ip_adapter") == snap / "models" / "ip-adapter_sd15.safetensors"
    assert (W.find("sd15") / "unet" / "config.json").is_file() and W.find("sam") is not None
    assert (snap / "models" / "image_encoder" / "model.safetensors").is_symlink()   # blobs + links, as the hub
    # HF_HUB_CACHE wins over HF_HOME, as in huggingface_hub
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "elsewhere"))
    assert W.find("sd15") is None
    monkeypatch.delenv("HF_HUB_CACHE")
    # a snapshot lacking a file (an interrupted download), or not the one refs/main names, is not used
    cache = copy_tree(caches / "hf", tmp_path / "hf")
    monkeypatch.setenv("HF_HOME", str(cache))
    repo = cache / "hub" / "models--lllyasviel--control_v11f1p_sd15_depth"
    assert W.find("controlnet_depth") is not None
    (repo / "refs" / "main").write_text("f" * 40)
    assert W.find("controlnet_depth") is None
    (repo / "refs" / "main").write_text("0123456789abcdef0123456789abcdef01234567")
    next((repo / "snapshots").iterdir()).joinpath("diffusion_pytorch_model.safetensors").unlink()
    assert W.find("controlnet_depth") is None


def test_lpips_heads_from_the_installed_lpips_package(tmp_path, monkeypatch):
    pkg = tmp_path / "site" / "lpips"
    (pkg / "weights" / "v0.1").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('importing lpips needs torchvision')\n")
    torch.save({f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate((64, 128, 256, 512, 512))},
               pkg / "weights" / "v0.1" / "vgg.pth")
    assert W.find("lpips") is None
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    assert W.locate("lpips") == (pkg / "weights" / "v0.1" / "vgg.pth", "lpips package")   # found, not imported


# ----------------------------------------------------------------------------- offline / downloads
def test_offline_missing_model_is_one_line_naming_the_fetch_command(tmp_path, monkeypatch, capsys):
    with pytest.raises(WeightsNotFound) as e:
        W.require("sd15")
    text = str(e.value)
    # short: what is missing, why, what fetching costs and the command that fetches it
    assert "\n" not in text and "ssgwarp weights --download sd15" in text and "SSGWARP_OFFLINE=1" in text
    assert "~4.27 GB" in text and len(text) < 250 and "--sd15 PATH or set SSGWARP_SD15" in text
    assert "model_index.json" not in text and "$SSGWARP_WEIGHTS" not in text
    with W.verbose():                 # --debug: the long form, every way to provide them
        with pytest.raises(WeightsNotFound) as e:
            W.require("sd15")
    text = str(e.value)
    for alt in ("--sd15", "SSGWARP_SD15", "$SSGWARP_WEIGHTS/stable-diffusion-v1-5", "model_index.json"):
        assert alt in text, alt
    assert "\n" not in text and not W._VERBOSE
    monkeypatch.delenv("SSGWARP_OFFLINE")
    with pytest.raises(WeightsNotFound, match="HF_HUB_OFFLINE=1"):
        W.require("raft")
    # the CLI: --offline is the reason; the stage that needs RAFT fails with one line, exit 2
    for var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        monkeypatch.delenv(var)
    assert main(["weights", "--download", "raft", "--offline"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "downloads are off (--offline)" in err[0]
    assert W.offline_reason() is None      # --offline lasts for one command


def test_download_only_when_allowed_and_asked_for_the_right_files(caches, tmp_path, monkeypatch, capsys):
    hub = FakeHub(monkeypatch, tmp_path)
    use(monkeypatch, tmp_path / "empty")
    for blocked in (lambda: W.require("ip_adapter"),                       # offline (the fixture)
                    lambda: W.require("ip_adapter", tmp_path / "nope.safetensors")):
        with pytest.raises(WeightsNotFound):
            blocked()
    use(monkeypatch, tmp_path / "empty", online=True)
    with pytest.raises(WeightsNotFound):
        W.require("ip_adapter", tmp_path / "nope.safetensors")             # a wrong explicit path: no download
    with pytest.raises(WeightsNotFound):
        W.require("ip_adapter", download=False)
    assert hub.calls == []
    # allowed: one announcement (what, where, size from the hub's metadata, licence), then the library call
    p = W.require("ip_adapter")
    cache = tmp_path / "empty" / "hf" / "hub"
    assert p == W.find("ip_adapter") and W.locate("ip_adapter")[1] == "Hugging Face cache"
    assert p.read_bytes() == b"weights of models/ip-adapter_sd15.safetensors"
    (_, repo, info_kw), (_, kw) = hub.calls
    assert repo == "h94/IP-Adapter" and info_kw["files_metadata"] and info_kw["timeout"] <= 10
    assert kw["repo_id"] == "h94/IP-Adapter" and kw["allow_patterns"] == ["models/ip-adapter_sd15.safetensors"]
    assert Path(kw["cache_dir"]) == cache and kw["etag_timeout"] <= 10
    err = capsys.readouterr().err
    assert "downloading ip_adapter" in err and "huggingface.co/h94/IP-Adapter" in err and "44.6 MB" in err
    assert "Apache-2.0" in err and ": 44.6 MB" in err      # the hub's figure for the allowed files only
    # the SD1.5 repo: only the diffusers files Stage 1 loads, not the multi-GB single-file checkpoints
    W.require("sd15")
    pats = hub.calls[-1][1]["allow_patterns"]
    assert "unet/diffusion_pytorch_model.safetensors" in pats and "tokenizer/*" in pats
    assert not any(p.endswith((".ckpt", ".bin")) or "v1-5-pruned" in p for p in pats)
    # either weights format: the first the repo has (here only .bin), and a snapshot holding it is complete
    p = W.require("controlnet_depth")
    assert hub.calls[-1][1]["allow_patterns"] == ["config.json", "diffusion_pytorch_model.bin"]
    assert (p / "diffusion_pytorch_model.bin").is_file() and W.find("controlnet_depth") == p
    assert "1.45 GB" in capsys.readouterr().err
    # torchvision weights: the published URL into TORCH_HOME/hub/checkpoints, hash prefix checked
    got = W.require("vgg16")
    _, url, dst, prefix = hub.calls[-1]
    assert url == "https://download.pytorch.org/models/vgg16-397923af.pth" and prefix == "397923af"
    assert Path(dst) == got == tmp_path / "empty" / "torch" / "hub" / "checkpoints" / "vgg16-397923af.pth"
    W.require("raft")
    assert hub.calls[-1][1] == "https://download.pytorch.org/models/raft_large_C_T_SKHT_V2-ff5fadd5.pth"


def test_failed_download_falls_back_once_with_one_line(tmp_path, monkeypatch, capsys):
    from ssgwarp.evaluation.features import load_extractor

    hub = FakeHub(monkeypatch, tmp_path, fail=OSError("[Errno -2] Name or service not known"))
    use(monkeypatch, tmp_path, online=True)
    ext = load_extractor()                              # VGG16 wanted, download fails: weight-free features
    assert ext.name == "random-multiscale:seed0,c128s2"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "downloading vgg16" in err[0]
    assert "download failed" in err[1] and "weight-free random multi-scale extractor" in err[1]
    n = len(hub.calls)
    with pytest.raises(WeightsNotFound, match="no network"):   # later models do not wait on the network again
        W.require("sd15")
    assert len(hub.calls) == n
    from ssgwarp.stylization.diffusion_models import Stage1Config, missing_weights
    assert len(missing_weights(Stage1Config())) == 4 and len(hub.calls) == n


def test_interrupted_or_wrong_download_leaves_nothing_behind(tmp_path, monkeypatch):
    """torch.hub.download_url_to_file itself (only its connection is faked): a connection that dies halfway and
    a file whose SHA-256 differs from the published prefix both end in a clear error and an empty folder."""
    import io

    import torch.hub

    use(monkeypatch, tmp_path, online=True)
    monkeypatch.setattr(W, "_url_size", lambda url: None)
    monkeypatch.setattr(W, "_connect", lambda host, port, timeout: None)     # the probe: reachable
    payload = b"0123456789" * 5000

    class Stream(io.BytesIO):
        def __init__(self, data, die):
            super().__init__(data)
            self.die = die

        def info(self):
            from email.message import Message
            m = Message()
            m["Content-Length"] = str(len(payload))
            return m

        def read(self, n=-1):
            if self.die and self.tell() > 20000:
                raise ConnectionResetError("connection reset by peer")
            return super().read(min(n, 8192) if n and n > 0 else 8192)

        def __exit__(self, *a):
            return False

    ck = tmp_path / "torch" / "hub" / "checkpoints"
    for die, match in ((True, "connection reset"), (False, "hash")):
        monkeypatch.setattr(torch.hub, "urlopen", lambda req, die=die: Stream(payload, die))
        monkeypatch.setattr(W, "_NETWORK_DOWN", None)
        with pytest.raises(WeightsNotFound, match=match) as e:
            W.require("raft")
        assert "ssgwarp weights --download raft" in str(e.value)
        assert list(ck.iterdir()) == []                 # no partial file, no final file


def test_corrupt_or_truncated_files_are_clear_errors(caches, tmp_path, monkeypatch):
    from ssgwarp.stylization.diffusion_models import Stage1Config, load_stage1
    from ssgwarp.evaluation.features import load_extractor
    from ssgwarp.evaluation.networks import load_raft

    root = copy_tree(caches, tmp_path / "c")
    use(monkeypatch, root)
    vgg = root / "torch" / "hub" / "checkpoints" / "vgg16-397923af.pth"
    vgg.write_bytes(vgg.read_bytes()[:1000])
    with pytest.raises(InputError, match="truncated, corrupt") as e:
        load_extractor()
    assert str(vgg) in str(e.value) and "ssgwarp weights --download vgg16 --force" in str(e.value)
    bad = tmp_path / "raft.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="raft.pth: cannot load RAFT state dict") as e:
        load_raft(bad)
    assert "replace it" in str(e.value)
    # a truncated safetensors blob in the Hugging Face cache
    unet = W.find("sd15") / "unet" / "diffusion_pytorch_model.safetensors"
    blob = unet.resolve()
    blob.chmod(0o644)
    blob.write_bytes(blob.read_bytes()[:5000])
    with pytest.raises(InputError) as e:
        load_stage1(Stage1Config(progress=False), "cpu")
    text = str(e.value)
    assert "\n" not in text and "cannot load the SD1.5 UNet" in text and "/unet" in text
    assert "ssgwarp weights --download sd15 --force" in text
    from ssgwarp.services.weights_command import verify
    ok, note = verify("sd15", W.find("sd15"))
    assert ok is False and "unet/diffusion_pytorch_model.safetensors" in note


# ----------------------------------------------------------------------------- `ssgwarp weights`
def test_weights_command_table(caches, tmp_path, monkeypatch, capsys):
    use(monkeypatch, caches)
    assert main(["weights", "--verify"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines()[2:] if line and not line.startswith("Hugging")}
    assert set(rows) == set(SPECS)
    for key in STAGE1 + ("sam",):
        assert "Hugging Face cache: " + str(caches / "hf" / "hub" / "models--") in rows[key], key
        assert rows[key].rstrip().endswith("ok"), key                 # blobs match their hub hashes
    assert "torch hub cache: " in rows["vgg16"] and "BAD" in rows["vgg16"]   # random weights under the real name
    assert "missing (ssgwarp weights --download raft)" in rows["raft"] and "~21.1 MB" in rows["raft"]
    assert "CreativeML OpenRAIL-M" in rows["sd15"] and "OpenRAIL" in rows["controlnet_depth"]
    assert "Apache-2.0" in rows["ip_adapter"] and "BSD-3-Clause" in rows["raft"]
    assert "downloads off (SSGWARP_OFFLINE=1)" in out
    # --download: groups expand, present models are kept, missing ones are fetched through the libraries
    hub = FakeHub(monkeypatch, tmp_path)
    use(monkeypatch, copy_tree(caches, tmp_path / "c"), online=True)
    assert main(["weights", "--download", "stage1", "evaluate"]) == 0
    out = capsys.readouterr().out
    assert out.count("already here") == 5
    assert [c[1] for c in hub.calls] == [SPECS["raft"].url, SPECS["lpips"].url]
    assert main(["weights", "--download", "vgg19"]) == 2
    assert "known models are" in capsys.readouterr().err
    # the --config file's "weights" mapping names a model's file (an explicit path wins over the caches)
    raft = tmp_path / "models" / "raft.pth"
    raft.parent.mkdir()
    torch.save({}, raft)
    (tmp_path / "cfg.json").write_text(json.dumps({"weights": {"raft": str(raft)}}))
    assert main(["weights", "--config", str(tmp_path / "cfg.json")]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith("raft")][0]
    assert str(raft) in row and "missing" not in row


def test_sam_spec_resolves_a_loadable_sam_model(caches, monkeypatch):
    from transformers import SamModel

    use(monkeypatch, caches)
    path = W.require("sam", None, None)
    model = SamModel.from_pretrained(str(path), local_files_only=True)
    assert model.config.vision_config.image_size == 64 and (path / "preprocessor_config.json").is_file()


# ----------------------------------------------------------------------------- end to end
def test_stylize_runs_stage1_and_stage2_from_the_caches_alone(caches, tmp_path, monkeypatch):
    """No SSGWARP_* variable, no explicit path: HF_HOME and TORCH_HOME only (offline, so nothing is fetched)."""
    from test_stylize import _write_run

    use(monkeypatch, caches)
    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--iters", "3", "--keyviews", "2",
                 "--max-side", "48", "--steps", "2", "--path-frames", "0", "--quiet", "--device", "cpu"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["stage1"]["ran"] is True and m["stage1"]["steps"] == 2
    assert m["extractor"] == "vgg16:conv3" and m["matching"].startswith("per group")
    assert (out / "keyviews" / "keyviews.json").is_file() and (out / "scene.ply").is_file()


# ----------------------------------------------------------------------------- one probe, one line per model
def test_no_network_is_probed_once_and_each_missing_model_said_once(tmp_path, monkeypatch, capsys):
    """Downloads allowed but no network: the first model wanted probes it (one connection attempt), every later one
    is reported missing at once; no download is attempted; a stage running without a model says so in one short
    line (its size and the command that fetches it), once per model however often it is asked for."""
    from ssgwarp.evaluation.features import load_extractor
    from ssgwarp.stylization.diffusion_models import Stage1Config, missing_weights

    hub = FakeHub(monkeypatch, tmp_path, fail=OSError("probe: [Errno -3] Temporary failure in name resolution"))
    use(monkeypatch, tmp_path, online=True)
    load_extractor()
    load_extractor()
    for key in ("raft", "lpips", "sd15"):
        with pytest.raises(WeightsNotFound, match=f"no local {key} weights \\(downloads are off: no network\\)"):
            W.require(key)
    assert len(missing_weights(Stage1Config())) == 4
    assert hub.probes == ["download.pytorch.org"] and hub.calls == []       # one probe, no download attempt
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no local vgg16 weights (downloads are off: no network)" in err[0]
    assert "`ssgwarp weights --download vgg16`" in err[0] and "~553 MB" in err[0] and len(err[0]) < 300
    assert "weight-free random multi-scale extractor" in err[0]
    with W.verbose():               # --debug: why (the probe's answer) and every way to provide it
        with pytest.raises(WeightsNotFound) as e:
            W.require("raft")
    assert "download.pytorch.org unreachable" in str(e.value) and "SSGWARP_RAFT" in str(e.value)
    assert hub.probes == ["download.pytorch.org"]


def test_reachable_network_is_probed_once_for_all_downloads(tmp_path, monkeypatch, capsys):
    hub = FakeHub(monkeypatch, tmp_path)
    use(monkeypatch, tmp_path, online=True)
    W.require("raft")
    W.require("ip_adapter")
    assert hub.probes == ["download.pytorch.org"] and len(hub.calls) == 3   # raft; ip_adapter: metadata + files


def test_evaluate_offline_says_each_missing_model_once(tmp_path, capsys):
    """`ssgwarp evaluate --offline` without weights: VGG16 (features, LPIPS trunk), RAFT and the LPIPS heads are
    each named once, in a short line; --debug gives the long form."""
    from test_stylize import _write_run

    run, _ = _write_run(tmp_path)
    args = ["evaluate", str(run), "--max-pairs", "1", "--path-frames", "3", "--device", "cpu", "--offline"]
    assert main(args) == 0
    cap = capsys.readouterr()
    text = cap.out + cap.err
    for key in ("vgg16", "raft", "lpips"):
        assert text.count(f"ssgwarp weights --download {key}`") == 1, key
    lines = [ln for ln in text.splitlines() if "ssgwarp weights --download" in ln]
    assert len(lines) == 3 and all(len(ln) < 300 and "(downloads are off: --offline)" in ln for ln in lines)
    assert main(args + ["--force", "--warp", "flow", "--debug"]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("ssgwarp: error: ") and "SSGWARP_RAFT" in last and "raft_large" in last


def test_stylize_checks_its_output_folder_before_fetching_anything(tmp_path, monkeypatch, capsys):
    """A taken --out is refused before any weights are fetched (the network is not even probed)."""
    from test_stylize import _write_run

    hub = FakeHub(monkeypatch, tmp_path)
    use(monkeypatch, tmp_path / "empty", online=True)
    run, style = _write_run(tmp_path)
    out = tmp_path / "styled"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    assert main(["stylize", str(run), "--style", str(style), "--out", str(out), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds a stylize output" in err[0] and "--force" in err[0]
    assert hub.calls == [] and hub.probes == []


def test_a_checkout_root_on_sys_path_is_refused_in_one_line_before_transformers_loads():
    """transformers 5 imports the registry package ``kernels``; with a checkout's root on ``sys.path`` (``python -m
    ssgwarp`` run there) its ``kernels/`` folder would be imported in its place. The library edits no ``sys.path``:
    it names the way out in one line before importing transformers, and lets the registry package through."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    probe = ("import sys\nfrom ssgwarp.services.weights import check_kernels_package\nfrom ssgwarp.errors import InputError\n"
             "for shadow in (False, True):\n"
             "    if shadow: sys.path.insert(0, {root!r})\n"
             "    try:\n        check_kernels_package(); print('ok', 'kernels' in sys.modules)\n"
             "    except InputError as e:\n        print('refused', 'kernels' in sys.modules, e)")
    r = subprocess.run([sys.executable, "-c", probe.format(root=str(root))], cwd=Path.home(), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    clean, shadowed = r.stdout.strip().splitlines()
    assert clean == "ok False"
    assert shadowed.startswith("refused False the source checkout's folder")
    assert str(root / "kernels") in shadowed and "installed `ssgwarp` command" in shadowed
