"""Instance masks (`ssgwarp masks`): cross-view association through the reconstruction, Segment Anything
plumbing on a tiny random SamModel in a fake Hugging Face cache, and mask-free groups that separate the
demo scene's objects.

The scene is the demo's procedural ground truth (ground, sphere, box, torus, cone; the object of every
Gaussian is known), seen by a ring of ten 80x60 cameras; its rendered object ids are the true
per-view instance masks. The run folder holds the true Gaussians as its "reconstruction" and the
rendered views as its capture (transforms.json), so `ssgwarp masks` and `ssgwarp group` run on it
as on any reconstruction.
"""
from __future__ import annotations

import contextlib
import io
import math
from pathlib import Path

import pytest
import torch

from ssgwarp import procedural as P

VIEWS, W, H = 10, 80, 60


def _main(argv):
    from ssgwarp.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def write_run(root: Path, scene, cams, images) -> Path:
    """A run folder (scene.ply, cameras.json, data.json) whose capture is ``images`` (transforms.json)."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.services.runs import data_json
    from ssgwarp.core.fileio import write_json
    from ssgwarp.formats.ply import write_ply

    P.write_transforms_dataset(root / "data", images, cams)
    data = load_dataset(root / "data")
    run = root / "run"
    run.mkdir(parents=True)
    write_ply(run / "scene.ply", scene)
    data.cameras.save(run / "cameras.json")
    write_json(run / "data.json", data_json(data))
    return run


@pytest.fixture(scope="module")
def truth():
    """(ground truth scene, cameras, images [C,H,W,3], object ids [C,H,W] with -1 = empty)."""
    gt = P.build_scene(0.5)
    cams = P.ring_cameras(VIEWS, W, H)
    images, objects = P.render_views(gt, cams)
    return gt, cams, images, objects


def perturb(objects: torch.Tensor, seed: int, p_split=0.4, p_merge=0.3, p_drop=0.25, specks=2) -> torch.Tensor:
    """Per-view masks as an independent segmenter might give them: each view's ids randomly renamed; with
    the given probabilities one mask split in two by a random line through its centroid, two masks
    merged, one mask dropped; plus ``specks`` tiny 2x2 masks of their own."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for lab in objects:
        ids = [int(i) for i in torch.unique(lab) if i >= 0]
        new = lab.clone()
        fresh = 100
        if float(torch.rand(1, generator=g)) < p_split:
            o = ids[int(torch.randint(len(ids), (1,), generator=g))]
            yy, xx = torch.nonzero(lab == o, as_tuple=True)
            ang = float(torch.rand(1, generator=g)) * math.pi
            side = ((yy - yy.float().mean()) * math.cos(ang) - (xx - xx.float().mean()) * math.sin(ang)) > 0
            new[yy[side], xx[side]] = fresh
            fresh += 1
        if float(torch.rand(1, generator=g)) < p_merge:
            a, b = torch.randperm(len(ids), generator=g)[:2].tolist()
            new[lab == ids[b]] = ids[a]
        if float(torch.rand(1, generator=g)) < p_drop:
            new[lab == ids[int(torch.randint(len(ids), (1,), generator=g))]] = -1
        for _ in range(specks):
            y, x = int(torch.randint(H - 2, (1,), generator=g)), int(torch.randint(W - 2, (1,), generator=g))
            new[y:y + 2, x:x + 2] = fresh
            fresh += 1
        vals = torch.unique(new)
        names = torch.randperm(5000, generator=g)[:vals.numel()] + 1
        renamed = torch.full_like(new, -1)
        for v, nm in zip(vals.tolist(), names.tolist()):
            if v >= 0:
                renamed[new == v] = nm
        out.append(renamed)
    return torch.stack(out)


def _ari_per_view_and_all(masks: torch.Tensor, objects: torch.Tensor) -> tuple[list[float], float]:
    """ARI of recovered masks against the true objects over the pixels an object covers (an ignored
    pixel, -1, counts as a label of its own, so it can only lower the score)."""
    from ssgwarp.grouping.association import adjusted_rand_index

    keep = objects >= 0
    per_view = [adjusted_rand_index(masks[v][keep[v]], objects[v][keep[v]]) for v in range(len(objects))]
    return per_view, adjusted_rand_index(masks[keep], objects[keep])


# ----------------------------------------------------------------------------- association

def test_adjusted_rand_index():
    from ssgwarp.grouping.association import adjusted_rand_index as ari

    a = torch.tensor([0, 0, 1, 1, 2, 2])
    assert ari(a, a) == 1.0 and ari(a, torch.tensor([7, 7, 3, 3, 9, 9])) == 1.0    # renaming does not matter
    # hand-computed: pairs within (0,0,1,1) vs (0,0,1,2): index 1, expected 2*1/6, max (2+1)/2
    assert ari(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 0, 1, 2])) == pytest.approx((1 - 1 / 3) / (1.5 - 1 / 3))
    assert ari(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 0, 1])) == pytest.approx(-0.5)
    g = torch.Generator().manual_seed(0)
    x, y = torch.randint(0, 4, (20000,), generator=g), torch.randint(0, 4, (20000,), generator=g)
    assert abs(ari(x, y)) < 0.01                                                  # independent labelings
    assert ari(torch.zeros(5), torch.zeros(5)) == 1.0


def test_blending_weight_sums_and_lifted_labels(truth):
    """gaussian_sums: the per-Gaussian weights of a view sum to its rendered alpha; lifting the true
    masks labels each seen Gaussian with its own object."""
    from ssgwarp.grouping.association import UNSEEN, compact_masks, lift_masks
    from ssgwarp.raster.rendering import gaussian_sums

    gt, cams, _, objects = truth
    ones = torch.ones(H, W, 1)
    w = gaussian_sums(gt.scene, cams[2], ones)
    _, alpha, _ = gt.scene.render(cams[[2]])
    assert w.shape == (len(gt), 1) and float(w.min()) >= 0
    assert float(w.sum()) == pytest.approx(float(alpha.sum()), rel=1e-4)
    compact, ids = compact_masks(objects, min_pixels=0)
    assert ids[0] == [0, 1, 2, 3, 4]                                   # every view sees the five objects
    for visible, want in ((0.05, 0.93), (0.5, 0.98)):
        # mislabelled Gaussians are the barely seen ones (behind an occluder's edge): fewer above 0.5 pixels
        labels, share = lift_masks(gt.scene, cams, compact, visible_weight=visible)
        assert bool(((labels == UNSEEN) == (share == 0)).all())
        firm = (share >= 0.5) & (labels >= 0)
        mapped = torch.stack([torch.tensor(ids[v])[labels[v].clamp_min(0)] for v in range(VIEWS)])
        agree = (mapped == gt.object_ids[None])[firm].double().mean()
        assert float(firm.double().mean()) > 0.3 and float(agree) > want


@pytest.mark.parametrize("seed", [0, 1])
def test_association_recovers_instances_from_perturbed_masks(truth, seed):
    """Per-view masks renamed at random, split, merged, dropped, with specks: the association recovers
    the five objects, ARI >= 0.95 in every view and over all views together (consistent ids)."""
    from ssgwarp.grouping.association import associate

    gt, cams, _, objects = truth
    given = perturb(objects, seed)
    res = associate(gt.scene, cams, given)
    per_view, overall = _ari_per_view_and_all(res.masks, objects)
    print(f"seed {seed}: K={res.num_instances}, ARI per view min {min(per_view):.4f}, all views {overall:.4f}, "
          f"{res.stats['edges']} edges, {res.stats['merges_refused']} merges refused")
    assert min(per_view) >= 0.95 and overall >= 0.95
    # the Gaussians of each object carry one label, and the five labels differ
    major = [int(torch.mode(res.labels[gt.object_ids == o]).values) for o in range(5)]
    assert len(set(major)) == 5 and 0 not in major
    # the given ids are mapped: a split object's two parts land in one instance
    assert len(res.mask_instance) == VIEWS and all(len(m) == len(i) for m, i in zip(res.mask_instance, res.mask_ids))


def test_association_objects_seen_in_few_views_and_background(truth):
    """The cone is labelled in only three of the ten views that see it and the ground in none (its pixels
    unlabelled, as a segmenter that leaves stuff out): the cone is still an instance of its own, also in
    a neighbouring view that did not label it, and the ground is background."""
    from ssgwarp.grouping.association import associate

    gt, cams, _, objects = truth
    given = objects.clone()
    given[given == 0] = -1                      # the ground: never masked
    given[3:][given[3:] == 4] = -1              # the cone: masked in views 0, 1 and 2 only
    res = associate(gt.scene, cams, given)
    on_cone = res.labels[gt.object_ids == 4]
    cone = int(torch.mode(on_cone).values)
    ground = int(torch.mode(res.labels[gt.object_ids == 0]).values)
    assert ground == 0 and cone > 0
    # the cone's side that views 0-2 see is the cone; its far side, never labelled, is background
    assert float((on_cone == cone).double().mean()) > 0.75
    others = {int(torch.mode(res.labels[gt.object_ids == o]).values) for o in (1, 2, 3)}
    assert cone not in others and len(others) == 3 and 0 not in others
    on = objects[3] == 4
    print(f"cone: {float((on_cone == cone).double().mean()):.3f} of its Gaussians; view 3: "
          f"{float((res.masks[3][on] == cone).double().mean()):.3f} of its pixels")
    assert float((res.masks[3][on] == cone).double().mean()) > 0.8


def test_masks_command_associates_given_view_masks_and_group_trains_on_them(truth, tmp_path):
    """`ssgwarp masks RUN --view-masks DIR` → RUN/object_mask + masks.json; `ssgwarp group RUN` finds them."""
    from ssgwarp.core.fileio import read_json
    from ssgwarp.grouping.stage import _read_id_image
    from ssgwarp.grouping.segment import write_id_image

    gt, cams, images, objects = truth
    run = write_run(tmp_path, gt.scene, cams, images)
    given = perturb(objects, 3)
    for v, name in enumerate(cams.names):
        write_id_image(tmp_path / "view_masks" / f"{name}.png", (given[v] + 1).numpy(), bits=16)
    code, out, err = _main(["masks", run, "--view-masks", tmp_path / "view_masks", "--quiet", "--device", "cpu"])
    assert code == 0, err
    rec = read_json(run / "masks.json")
    assert rec["source"]["kind"] == "view masks" and rec["ignore_id"] == 255 and rec["bits"] == 8
    assert rec["num_instances"] >= 5 and len(rec["segmented_views"]) == len(rec["train_views"])
    files = sorted(p.name for p in (run / "object_mask").iterdir())
    assert files == sorted(f"{n}.png" for n in cams.names)                  # every camera, held-out ones too
    written = torch.stack([torch.from_numpy(_read_id_image(run / "object_mask" / f)) for f in files])
    recovered = torch.where(written == 255, torch.full_like(written, -1), written)
    per_view, overall = _ari_per_view_and_all(recovered, objects)
    assert min(per_view) >= 0.95 and overall >= 0.95
    # an existing result is not overwritten
    code, _, err = _main(["masks", run, "--view-masks", tmp_path / "view_masks", "--quiet"])
    assert code == 2 and "--force" in err and len(err.strip().splitlines()) == 1
    # group trains on them (auto finds RUN/object_mask; the ignore id comes from masks.json)
    code, out, err = _main(["group", run, "--iters", "40", "--quiet", "--device", "cpu"])
    assert code == 0, err
    info = read_json(run / "groups" / "groups.json")
    assert info["kind"] == "given masks" and info["mask_dir"] == str(run / "object_mask")
    assert info["masks_record"]["num_instances"] == rec["num_instances"]
    assert info["train_mask_accuracy"] > 0.9 and "given masks" in out


# ----------------------------------------------------------------------------- Segment Anything

def _fake_hf_cache(hf_home: Path) -> Path:
    """A Hugging Face cache (real layout: blobs, snapshot links, refs/main) under ``hf_home/hub`` holding a
    tiny random SamModel as facebook/sam-vit-base. Returns the snapshot folder."""
    from fakeweights import _tree, hf_cache_entry, save_tiny_sam

    from ssgwarp.services.weight_specs import SPECS

    saved = save_tiny_sam(hf_home.parent / "tiny_sam", seed=0)
    return hf_cache_entry(hf_home / "hub", SPECS["sam"].repo, _tree(saved))


def test_mask_filters_nms_and_painting():
    from ssgwarp.grouping.segment import MaskConfig, mask_nms, paint_label_map, point_grid, select_masks, stability_scores

    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    sharp = torch.where((xx < 16) & (yy < 16), 20.0, -20.0)                 # a square with sharp edges
    twin = torch.where((xx < 16) & (yy < 15), 20.0, -20.0)                  # nearly the same square
    soft = 8.0 - 0.5 * (xx + yy)                                            # a blurry ramp
    other = torch.where(xx >= 20, 20.0, -20.0)
    logits = torch.stack([sharp, twin, soft, other])
    st = stability_scores(logits, 0.0, 1.0)
    assert st[0] == 1.0 and st[1] == 1.0 and float(st[2]) < 0.9
    iou = torch.tensor([0.95, 0.93, 0.97, 0.5])
    kept, scores = select_masks(logits, iou, MaskConfig(pred_iou_thresh=0.88, stability_thresh=0.95, nms_thresh=0.7))
    # the soft ramp fails stability, `other` fails predicted IoU, the twin is suppressed by the better square
    assert kept.shape[0] == 1 and torch.equal(kept[0], sharp) and float(scores[0]) == pytest.approx(0.95)
    kept, _ = select_masks(logits, iou, MaskConfig(pred_iou_thresh=0.0, stability_thresh=0.0, nms_thresh=0.99))
    assert kept.shape[0] == 4
    assert mask_nms(logits > 0, iou, 0.7).tolist() == [2, 0, 3]            # best first, twin dropped
    big = torch.zeros(4, 6, dtype=torch.bool)
    big[:, :5] = True
    small = torch.zeros(4, 6, dtype=torch.bool)
    small[1:3, 1:3] = True
    lab = paint_label_map(torch.stack([small, big]))
    assert lab[1, 1] == 0 and lab[0, 0] == 1 and lab[0, 5] == -1            # the smaller mask stays on top
    pts = point_grid(2, 4, 2)
    assert pts.tolist() == [[1.0, 0.5], [3.0, 0.5], [1.0, 1.5], [3.0, 1.5]]


def test_masks_command_with_tiny_sam_from_hf_cache(truth, tmp_path, monkeypatch, fail_on_call):
    """A tiny random SamModel saved with save_pretrained in the Hugging Face cache layout, found offline
    through HF_HOME: `ssgwarp masks` segments every training view (batched prompts), associates, writes the
    layout; after Ctrl-C `--resume` segments only the views left; `group --joint` trains on the result."""
    import ssgwarp.grouping.segment as M
    from ssgwarp.core.fileio import read_json

    gt, cams, images, objects = truth
    run = write_run(tmp_path, gt.scene, cams, images)
    snap = _fake_hf_cache(tmp_path / "hf")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))        # offline, no other weights: conftest
    argv = ["masks", run, "--points-per-side", "6", "--points-per-batch", "16", "--pred-iou-thresh", "0",
            "--stability-thresh", "0", "--quiet", "--device", "cpu"]
    # Ctrl-C while segmenting the third view: the two finished views are kept, nothing else is written
    orig = fail_on_call(M, "generate_masks", 3, "interrupt")
    code, _, err = _main(argv)
    assert code == 130 and "--resume" in err
    assert len(list((run / "sam_masks").glob("*.png"))) == 2
    assert not (run / "object_mask").exists() and not (run / "masks.json").exists()
    monkeypatch.setattr(M, "generate_masks", orig)
    calls = {"n": 0}
    real = M.SamSegmenter.decode

    def counting(self, emb, points):
        calls["n"] += 1
        assert points.shape[0] <= 16                                        # --points-per-batch
        return real(self, emb, points)

    monkeypatch.setattr(M.SamSegmenter, "decode", counting)
    code, out, err = _main(argv + ["--resume"])
    assert code == 0, err
    rec = read_json(run / "masks.json")
    train = rec["train_views"]
    assert calls["n"] == (len(train) - 2) * math.ceil(36 / 16)            # 36 prompts per view, 3 batches
    assert sum(bool(v.get("resumed")) for v in rec["segmented_views"]) == 2
    assert rec["source"]["kind"] == "segmenter" and Path(rec["source"]["weights"]) == snap
    assert rec["source"]["image_size"] == 64 and rec["num_instances"] >= 1
    assert all(v["masks"] >= 1 for v in rec["segmented_views"])
    raw = sorted(p.name for p in (run / "sam_masks").glob("*.png"))
    assert raw == sorted(f"{Path(n).stem}.png" for n in train)
    assert len(list((run / "object_mask").iterdir())) == len(cams)
    assert f"{rec['num_instances']} instances" in out
    # a finished run resumes without segmenting again; other settings are refused
    monkeypatch.setattr(M.SamSegmenter, "decode", lambda *a: pytest.fail("re-segmented a finished view"))
    code, _, err = _main(argv + ["--resume"])
    assert code == 0, err
    assert read_json(run / "masks.json")["num_instances"] == rec["num_instances"]
    code, _, err = _main([a if a != "6" else "5" for a in argv] + ["--resume"])
    assert code == 2 and "other settings" in err
    # joint training with the reconstruction takes them too
    from ssgwarp.grouping.stage import group_scene
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.reconstruction.recipe import Recipe

    info = group_scene(run, joint=True, config=GroupConfig(dim=8), progress=False,
                       reconstruct_kwargs={"iters": 6, "recipe": Recipe(init_max_points=300)})
    assert info["kind"] == "segmenter instances" and info["joint"]
    assert info["masks_record"]["source"]["kind"] == "segmenter"


def test_missing_sam_weights_is_one_line_naming_the_fetch_command(truth, tmp_path, monkeypatch):
    gt, cams, images, _ = truth
    run = write_run(tmp_path, gt.scene, cams, images)
    code, _, err = _main(["masks", run, "--quiet"])          # conftest: empty caches, downloads off
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "ssgwarp weights --download sam" in err and "--sam" in err and "SSGWARP_SAM" in err
    assert not (run / "object_mask").exists() and not (run / "masks.json").exists()
    code, _, err = _main(["masks", run, "--sam", tmp_path / "nowhere", "--quiet"])
    assert code == 2 and str(tmp_path / "nowhere") in err and "does not exist" in err


# ----------------------------------------------------------------------------- mask-free groups

def reconstruction_like(gt, seed: int = 0, colour_noise: float = 0.2, floaters: float = 0.3):
    """The true Gaussians as a reconstruction leaves them: each colour off by N(0, colour_noise) (colours
    that compensate for each other where Gaussians overlap) and ``floaters`` times as many faint,
    randomly coloured Gaussians in the air."""
    from ssgwarp.raster.scene import GaussianScene, rgb_to_sh_dc

    g = torch.Generator().manual_seed(seed)
    s = gt.scene
    n, m = len(s), int(len(s) * floaters)
    rgb = (s.base_colors + torch.randn(n, 3, generator=g) * colour_noise).clamp(0, 1)
    pos = torch.rand(m, 3, generator=g) * torch.tensor([4.4, 4.4, 1.5]) - torch.tensor([2.2, 2.2, 0.0])
    quats = torch.zeros(m, 4)
    quats[:, 0] = 1
    return GaussianScene(torch.cat([s.means, pos]), torch.cat([s.log_scales, torch.full((m, 3), math.log(0.08))]),
                         torch.cat([s.quats, quats]), torch.cat([s.logit_opacities, torch.full((m,), -1.7)]),
                         rgb_to_sh_dc(torch.cat([rgb, torch.rand(m, 3, generator=g)])))


@pytest.mark.slow  # mask-free grouping of the whole demo scene (~3.5 s on 2 cores)
def test_mask_free_groups_separate_the_demo_objects(truth, tmp_path):
    """`ssgwarp group` without masks on the demo scene with noisy colours and floaters: clustering on
    the captured colour lifted onto the Gaussians finds the five objects (each in a group of its own,
    purity >= 0.95 of the group maps against the true objects); on the Gaussians' own colours it does not."""
    from ssgwarp.demo import group_agreement
    from ssgwarp.grouping.stage import group_scene
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.raster.groups import render_group_maps
    from ssgwarp.formats.ply import read_ply
    from ssgwarp.grouping.pseudomasks import ClusterConfig, cluster_gaussians, render_label_masks

    gt, cams, images, objects = truth
    noisy = reconstruction_like(gt)
    run = write_run(tmp_path, noisy, cams, images)
    info = group_scene(run, masks="auto", config=GroupConfig(iters=60), progress=False)
    assert info["kind"] == "mask-free clusters" and "images" in info["criterion"]["colour"]
    grouped = read_ply(run / "scene.ply")
    labels, _ = render_group_maps(grouped, cams, load_groups(run).classifier)
    agree = group_agreement(labels, objects, 5)
    print(f"mask-free on the demo scene: K={info['num_groups']}, {agree}")
    assert agree["separated"] == 5 and agree["purity"] >= 0.95
    # the measurement behind it: the Gaussians' own colours merge objects
    own = cluster_gaussians(noisy, cams, config=ClusterConfig(colour="gaussians"), seed=0)
    m = render_label_masks(noisy, cams, own.labels, own.num_groups, alpha_min=0.0, share_min=0.0)
    assert group_agreement(m, objects, 5)["separated"] < 5
