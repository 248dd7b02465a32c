"""Gaussian Grouping (`ssgwarp group`): identities, classifier, masks, the mask-free path, outputs, CLI.

The synthetic scene: three coloured blobs of Gaussians on a grey ground plane
(object id known per Gaussian), seen by a ring of ten 48x48 cameras; views 4
and 9 are held out. Ground-truth masks are the known ids rendered through the
rasterizer.
"""
from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ssgwarp.core.cameras import Cameras, intrinsics, look_at
from ssgwarp.errors import InputError
from ssgwarp.raster.scene import GaussianScene, rgb_to_sh_dc

SIZE = 48
TRAIN = [0, 1, 2, 3, 5, 6, 7, 8]
TEST = [4, 9]


# -- the synthetic scene --------------------------------------------------------------------

def blobs_scene(seed: int = 0, n_plane: int = 12, n_blob: int = 40) -> tuple[GaussianScene, torch.Tensor]:
    """A grey plane (id 0) and red, green, blue blobs (ids 1..3): ``(scene, object id [N])``."""
    g = torch.Generator().manual_seed(seed)
    xs = torch.linspace(-1.2, 1.2, n_plane)
    px, py = torch.meshgrid(xs, xs, indexing="ij")
    plane = torch.stack([px.flatten(), py.flatten(), torch.zeros(n_plane * n_plane)], 1)
    plane = plane + torch.randn(plane.shape, generator=g) * 0.01
    spacing = 2.4 / (n_plane - 1)
    centres = torch.tensor([[0.55, 0.0, 0.25], [-0.3, 0.5, 0.25], [-0.3, -0.5, 0.25]])
    colours = torch.tensor([[0.9, 0.15, 0.1], [0.1, 0.8, 0.2], [0.15, 0.25, 0.9]])
    pts = [plane]
    rgb = [0.5 + torch.randn(plane.shape[0], 3, generator=g) * 0.03]
    oid = [torch.zeros(plane.shape[0], dtype=torch.long)]
    logs = [torch.log(torch.tensor([spacing * 0.6, spacing * 0.6, 0.02])).repeat(plane.shape[0], 1)]
    for i in range(3):
        pts.append(centres[i] + torch.randn(n_blob, 3, generator=g) * 0.11)
        rgb.append((colours[i] + torch.randn(n_blob, 3, generator=g) * 0.03).clamp(0, 1))
        oid.append(torch.full((n_blob,), i + 1, dtype=torch.long))
        logs.append(torch.full((n_blob, 3), math.log(0.07)))
    xyz, rgb, oid, logs = torch.cat(pts), torch.cat(rgb), torch.cat(oid), torch.cat(logs)
    n = xyz.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    logit = torch.full((n,), math.log(0.95 / 0.05))
    return GaussianScene(xyz, logs, quats, logit, rgb_to_sh_dc(rgb)), oid


def ring_cameras(n: int = 10, size: int = SIZE) -> Cameras:
    ang = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    eyes = torch.stack([2.6 * torch.cos(ang), 2.6 * torch.sin(ang), torch.full_like(ang, 1.6)], 1)
    vm = look_at(eyes, torch.zeros(n, 3, dtype=torch.float64), up=(0, 0, 1)).float()
    return Cameras(vm, intrinsics(float(size), float(size), size / 2, size / 2, n), size, size,
                   [f"view{i:02d}.png" for i in range(n)])


def gt_masks(scene, cams, oid):
    from ssgwarp.grouping.pseudomasks import render_label_masks

    return render_label_masks(scene, cams, oid, int(oid.max()) + 1)


def best_match_accuracy(pred: torch.Tensor, gt: torch.Tensor) -> float:
    """Pixel accuracy of ``pred`` against ``gt`` (>= 0 pixels) under the best one-to-one label matching."""
    valid = gt >= 0
    p, t = pred[valid].flatten().long(), gt[valid].flatten().long()
    k = int(max(p.max(), t.max())) + 1
    conf = torch.zeros(k, k, dtype=torch.long)
    conf.index_put_((p, t), torch.ones_like(p), accumulate=True)
    best = max(sum(int(conf[perm[j], j]) for j in range(k)) for perm in itertools.permutations(range(k)))
    return best / max(1, t.numel())


def make_run(root: Path, scene: GaussianScene, cams: Cameras, data_dir: str | None = None) -> Path:
    """A run folder as reconstruction writes it (scene.ply, cameras.json, data.json)."""
    from ssgwarp.core.fileio import write_json
    from ssgwarp.formats.ply import write_ply

    root.mkdir(parents=True, exist_ok=True)
    write_ply(root / "scene.ply", scene)
    cams.save(root / "cameras.json")
    write_json(root / "data.json", {"data_dir": data_dir, "images": "images",
                                    "split": {"train": [cams.names[i] for i in TRAIN],
                                              "test": [cams.names[i] for i in TEST]},
                                    "background": [1.0, 1.0, 1.0]})
    return root


@pytest.fixture(scope="module")
def synth():
    scene, oid = blobs_scene()
    cams = ring_cameras()
    return scene, oid, cams, gt_masks(scene, cams, oid)


# -- the rasterizer carries identity channels like colour ---------------------------------------

def test_identity_channels_match_torch_reference(synth):
    reference = pytest.importorskip("ssgwarp.raster.reference")
    from ssgwarp.raster.rasterize import rasterization

    scene, _, cams, _ = synth
    g = torch.Generator().manual_seed(1)
    ids = torch.randn(len(scene), 16, generator=g).double()
    s = scene.to(dtype=torch.float64)
    c = cams[[4]].to(dtype=torch.float64)
    outs = []
    for fn in (rasterization, reference.rasterization_reference):
        e = ids.clone().requires_grad_(True)
        colors = torch.cat([s.base_colors, e], dim=1)
        img, alpha, _ = fn(s.means, s.quats, s.scales, s.opacities, colors, c.viewmats, c.Ks, SIZE, SIZE)
        w = torch.linspace(-1, 1, img[..., 3:].numel(), dtype=img.dtype).reshape(img[..., 3:].shape)
        (img[..., 3:] * w).sum().backward()
        outs.append((img.detach(), alpha.detach(), e.grad.clone()))
    (i0, a0, g0), (i1, a1, g1) = outs
    assert i0.shape == (1, SIZE, SIZE, 19)
    assert float(i0[..., 3:].abs().max()) > 0.1                     # the identities really render
    torch.testing.assert_close(i0, i1, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(a0, a1, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(g0, g1, rtol=1e-6, atol=1e-8)
    # the scene's own path puts identity channels after RGB in the same pass
    s2 = s.replace(identities=ids)
    img2, _, _ = s2.render(c, identities=True)
    torch.testing.assert_close(img2, i0, rtol=1e-6, atol=1e-8)


# -- losses -----------------------------------------------------------------------------------------

def test_mask_loss_and_3d_regulariser():
    from ssgwarp.core.geometry import knn_indices
    from ssgwarp.grouping.model import make_classifier, mask_loss, regularizer_3d

    g = torch.Generator().manual_seed(0)
    logits = torch.randn(5, 7, 4, generator=g)
    t = torch.randint(0, 4, (5, 7), generator=g)
    t[0] = -1
    want = torch.nn.functional.cross_entropy(logits[1:].reshape(-1, 4), t[1:].reshape(-1)) / math.log(4)
    torch.testing.assert_close(mask_loss(logits, t, 4), want)
    assert float(mask_loss(logits, torch.full_like(t, -1), 4)) == 0.0

    pts = torch.rand(200, 3, generator=g)
    q = torch.arange(0, 200, 7)
    nn_idx = knn_indices(pts[q], pts, 5, exclude=q, block=len(q) * 64)  # blocks of 64 points
    d = torch.cdist(pts[q], pts)
    d[torch.arange(len(q)), q] = float("inf")
    assert torch.equal(nn_idx.sort(1).values, d.topk(5, largest=False).indices.sort(1).values)

    clf = make_classifier(8, 3, generator=g)
    same = torch.randn(1, 8, generator=g).repeat(200, 1)
    assert float(regularizer_3d(same, pts, clf, generator=g, samples=50).detach()) == pytest.approx(0.0, abs=1e-7)
    # identities that change with x disagree between neighbours; smooth ones less than random ones
    rough = (torch.randn(200, 8, generator=g) * 3).requires_grad_(True)
    r_rough = regularizer_3d(rough, pts, clf, generator=torch.Generator().manual_seed(3), samples=100)
    smooth = (pts[:, :1] * torch.randn(1, 8, generator=g) * 3)
    r_smooth = regularizer_3d(smooth, pts, clf, generator=torch.Generator().manual_seed(3), samples=100)
    assert float(r_rough.detach()) > float(r_smooth.detach()) > 0
    r_rough.backward()
    assert rough.grad is not None and float(rough.grad.abs().sum()) > 0


def test_regulariser_with_a_neighbour_table_equals_the_search():
    """On positions that do not move, the regulariser given each Gaussian's neighbours once
    (``neighbour_table``) draws the same samples as the search per call and gives the same value and
    gradients (identities and classifier) as the definition: the classifier over every Gaussian, the
    KL of each sample against its k nearest others."""
    from ssgwarp.core.geometry import knn_indices
    from ssgwarp.grouping.model import GroupConfig, make_classifier, neighbour_table, regularizer_3d

    g = torch.Generator().manual_seed(6)
    n, k = 600, 5
    pts = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.0, 0.5])
    ids0 = torch.randn(n, 8, generator=g)
    clf = make_classifier(8, 4, generator=g)
    table = neighbour_table(pts, GroupConfig(reg_k=k))
    assert table.shape == (n, k)

    def spec(ids, seed):   # the definition, written out (with the per-call search's draws)
        gen = torch.Generator().manual_seed(seed)
        q = torch.randperm(n, generator=gen)[:150]
        nbr = knn_indices(pts[q], pts, k, exclude=q)
        logp = torch.log_softmax(clf(ids), dim=-1)
        kl = (logp[q][:, None].exp() * (logp[q][:, None] - logp[nbr])).sum(-1)
        return kl.mean() / logp.shape[1]

    results = []
    for how in ("spec", "search", "table"):
        ids = ids0.clone().requires_grad_(True)
        clf.zero_grad()
        if how == "spec":
            r = spec(ids, 11)
        else:
            r = regularizer_3d(ids, pts, clf, generator=torch.Generator().manual_seed(11), k=k, samples=150,
                               neighbours=table if how == "table" else None)
        r.backward()
        results.append((r.detach(), ids.grad, clf.weight.grad.clone(), clf.bias.grad.clone()))
    assert float(results[0][0]) > 0 and float(results[0][1].abs().sum()) > 0
    for other in results[1:]:
        for a, b in zip(results[0], other):
            torch.testing.assert_close(b, a, atol=1e-6, rtol=1e-6)
    # no table where the neighbours come from a random pool, or with the regulariser off
    assert neighbour_table(pts, GroupConfig(reg_max_points=100)) is None
    assert neighbour_table(pts, GroupConfig(reg_weight=0.0)) is None


# -- masks from outside --------------------------------------------------------------------------------

def _write_masks(folder: Path, labels: torch.Tensor, names, values=(0, 10, 20, 30), ignore=255):
    from ssgwarp.core.fileio import write_image

    folder.mkdir(parents=True, exist_ok=True)
    lut = torch.tensor(list(values))
    for lab, name in zip(labels, names):
        ids = torch.where(lab >= 0, lut[lab.clamp_min(0)], torch.full_like(lab, ignore))
        write_image(folder / f"{Path(name).stem}.png", ids.float().numpy() / 255.0)


def test_given_masks_heldout_accuracy(tmp_path, synth):
    """Masks at 2x resolution with sparse ids → group maps of held-out views >= 95% (best matching)."""
    from ssgwarp.cli import main
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.raster.groups import gaussian_groups, render_group_maps
    from ssgwarp.formats.ply import read_ply

    scene, oid, cams, gt = synth
    big = cams.rescaled(2 * SIZE, 2 * SIZE)
    gt_big = gt_masks(scene, big[TRAIN], oid)
    _write_masks(tmp_path / "object_mask", gt_big, [cams.names[i] for i in TRAIN])
    run = make_run(tmp_path / "run", scene, cams)
    rc = main(["group", str(run), "--masks", str(tmp_path / "object_mask"), "--ignore-id", "255",
               "--iters", "60", "--quiet"])
    assert rc == 0
    info = json.loads((run / "groups" / "groups.json").read_text())
    assert info["num_groups"] == 4 and info["mask_ids"] == [0, 10, 20, 30] and info["method"] == "masks"
    model = load_groups(run)
    grouped = read_ply(run / "scene.ply")
    assert grouped.identities is not None and grouped.identities.shape == (len(scene), 16)
    labels, probs = render_group_maps(grouped, cams[TEST], model.classifier)
    assert labels.shape == (2, SIZE, SIZE) and probs.shape == (2, SIZE, SIZE, 4)
    torch.testing.assert_close(probs.sum(-1), torch.ones(2, SIZE, SIZE))
    acc = best_match_accuracy(labels, gt[TEST])
    print(f"held-out group-map accuracy from given masks: {acc:.4f}")
    assert acc >= 0.95
    # groups are numbered as the masks' compact ids: no permutation needed here
    assert float((labels == gt[TEST])[gt[TEST] >= 0].double().mean()) >= 0.95
    ids, prob = gaussian_groups(grouped, model.classifier)
    assert ids.shape == (len(scene),) and bool(((prob > 0) & (prob <= 1)).all())
    visible_blobs = oid > 0
    assert float((ids[visible_blobs] == oid[visible_blobs]).double().mean()) > 0.9


def test_mask_validation_errors(tmp_path, synth):
    from ssgwarp.core.fileio import write_image
    from ssgwarp.grouping.mask_files import load_masks

    scene, oid, cams, gt = synth
    names = [cams.names[i] for i in TRAIN]
    with pytest.raises(InputError, match="folder not found"):
        load_masks(tmp_path / "nope", names, SIZE, SIZE)
    _write_masks(tmp_path / "m", gt[TRAIN[:-1]], names[:-1])
    with pytest.raises(InputError, match="view08"):
        load_masks(tmp_path / "m", names, SIZE, SIZE)
    # a mask for the held-out image may be missing when it is not required
    ms = load_masks(tmp_path / "m", names, SIZE, SIZE, required=[True] * 7 + [False], ignore_id=255)
    assert ms.num_groups == 4 and bool((ms.targets[-1] == -1).all())
    with pytest.raises(InputError, match="4 distinct ids.*--groups is 3"):
        load_masks(tmp_path / "m", names[:-1], SIZE, SIZE, num_groups=3, ignore_id=255)
    assert load_masks(tmp_path / "m", names[:-1], SIZE, SIZE, num_groups=6, ignore_id=255).num_groups == 6
    wide = tmp_path / "wide"
    wide.mkdir()
    for nm in names:
        write_image(wide / f"{Path(nm).stem}.png", np.zeros((SIZE, 2 * SIZE), np.float32))
    with pytest.raises(InputError, match="aspect"):
        load_masks(wide, names, SIZE, SIZE)
    colour = tmp_path / "colour"
    colour.mkdir()
    for nm in names:
        write_image(colour / f"{Path(nm).stem}.png", np.random.default_rng(0).random((SIZE, SIZE, 3)).astype(np.float32))
    with pytest.raises(InputError, match="single-channel"):
        load_masks(colour, names, SIZE, SIZE)


# -- the mask-free path ---------------------------------------------------------------------------

def test_mask_free_path_heldout_accuracy_and_outputs(tmp_path, synth):
    from ssgwarp.cli import main
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.raster.groups import render_group_maps
    from ssgwarp.formats.ply import read_ply

    scene, oid, cams, gt = synth
    run = make_run(tmp_path / "run", scene, cams)
    assert main(["group", str(run), "--iters", "60", "--quiet"]) == 0
    info = json.loads((run / "groups" / "groups.json").read_text())
    # the scene has 4 objects: the criterion finds exactly them, and stays within the cap
    assert info["num_groups"] == 4
    assert info["criterion"]["name"] == "eigengap" and info["criterion"]["chosen_k"] == 4
    assert len(info["groups"]) == 4 and sum(g["gaussians"] for g in info["groups"]) == len(scene)
    assert sum(g["screen_coverage"] for g in info["groups"]) == pytest.approx(1.0)
    assert info["reprojection_agreement"]["mean"] > 0.95
    maps = sorted(p.name for p in (run / "groups" / "group_maps").iterdir())
    assert maps == [f"view{i:02d}.png" for i in range(10)]
    assert (run / "groups" / "classifier.pt").is_file() and (run / "groups" / "groups.png").is_file()
    assert not (run / "groups" / "checkpoint.pt").exists()
    grouped = read_ply(run / "scene.ply")
    model = load_groups(run)
    assert model.num_groups == 4 and model.dim == 16
    labels, _ = render_group_maps(grouped, cams[TEST], model.classifier)
    acc = best_match_accuracy(labels, gt[TEST])
    print(f"held-out group-map accuracy, mask-free: {acc:.4f}; "
          f"reprojection agreement {info['reprojection_agreement']['mean']:.4f}")
    assert acc >= 0.95
    # the group map PNGs use the shared palette
    from ssgwarp.core.fileio import read_image
    from ssgwarp.core.palette import palette

    png = read_image(run / "groups" / "group_maps" / "view04.png", 3)
    full, _ = render_group_maps(grouped, cams[[4]], model.classifier)
    want = palette(4)[full[0].numpy()]
    assert np.abs(png - want).max() <= 1.0 / 255 + 1e-6
    # a second run refuses to overwrite without --force, then works with it
    assert main(["group", str(run), "--quiet"]) == 2
    assert main(["group", str(run), "--iters", "5", "--groups", "2", "--force", "--quiet"]) == 0
    assert json.loads((run / "groups" / "groups.json").read_text())["num_groups"] == 2


def test_cap_and_min_fraction():
    """The cap bounds K and tiny clusters are merged away (model only what the scene requires)."""
    from ssgwarp.grouping.pseudomasks import ClusterConfig, cluster_gaussians

    scene, oid = blobs_scene(n_blob=40)
    # add a 3-Gaussian yellow speck: too small to keep as a group
    speck = scene.subset(torch.arange(3)).replace(
        means=torch.tensor([[0.9, 0.9, 0.3], [0.92, 0.9, 0.3], [0.9, 0.92, 0.3]]),
        sh_dc=rgb_to_sh_dc(torch.tensor([[0.95, 0.9, 0.1]] * 3)))
    both = GaussianScene(*(torch.cat([a, b]) for a, b in zip(
        (scene.means, scene.log_scales, scene.quats, scene.logit_opacities, scene.sh_dc),
        (speck.means, speck.log_scales, speck.quats, speck.logit_opacities, speck.sh_dc))))
    res = cluster_gaussians(both, ring_cameras(), seed=0)
    assert res.num_groups == 4 and res.criterion["merged"]
    capped = cluster_gaussians(scene, ring_cameras(), config=ClusterConfig(max_groups=3), seed=0)
    assert capped.num_groups <= 3


# -- determinism, interruption and resume ------------------------------------------------------------

def test_deterministic_for_a_seed_and_resume_after_interrupt(tmp_path, synth, monkeypatch, fail_on_call):
    import ssgwarp.grouping.train as grouping  # (the training loop calls mask_loss there)
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.grouping.train import train_identities
    from ssgwarp.grouping.pseudomasks import pseudo_masks

    scene, oid, cams, gt = synth
    tc = cams[TRAIN]
    m1, r1 = pseudo_masks(scene, tc, seed=5)
    m2, r2 = pseudo_masks(scene, tc, seed=5)
    assert torch.equal(m1, m2) and torch.equal(r1.labels, r2.labels)
    cfg = GroupConfig(iters=12, reg_every=2, checkpoint_every=0)
    a = train_identities(scene, tc, m1, r1.num_groups, config=cfg, seed=3, progress=False)
    b = train_identities(scene, tc, m1, r1.num_groups, config=cfg, seed=3, progress=False)
    c = train_identities(scene, tc, m1, r1.num_groups, config=cfg, seed=4, progress=False)
    assert torch.equal(a[0].identities, b[0].identities)
    assert torch.equal(a[1].weight, b[1].weight) and torch.equal(a[1].bias, b[1].bias)
    assert not torch.equal(a[0].identities, c[0].identities)
    # geometry is frozen
    for name in ("means", "log_scales", "quats", "logit_opacities", "sh_dc"):
        assert torch.equal(getattr(a[0], name), getattr(scene, name))

    # Ctrl-C at step 7 writes a checkpoint; resuming reproduces the uninterrupted run exactly
    real = fail_on_call(grouping, "mask_loss", 8, "interrupt")
    ck = tmp_path / "checkpoint.pt"
    with pytest.raises(KeyboardInterrupt):
        train_identities(scene, tc, m1, r1.num_groups, config=cfg, seed=3, progress=False, checkpoint_path=ck)
    monkeypatch.setattr(grouping, "mask_loss", real)
    assert ck.is_file() and torch.load(ck, weights_only=False)["step"] == 7
    d = train_identities(scene, tc, m1, r1.num_groups, config=cfg, seed=3, progress=False, checkpoint_path=ck,
                         resume=True)
    assert torch.equal(d[0].identities, a[0].identities) and torch.equal(d[1].weight, a[1].weight)


# -- joint training with reconstruction -------------------------------------------------------------

def test_grouping_hook_trains_with_reconstruction(synth):
    rec = pytest.importorskip("ssgwarp.reconstruction.reconstruct")
    from ssgwarp.reconstruction.strategy import DefaultStrategy
    from ssgwarp.capture.datasets import SceneData
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.grouping.train import GroupingHook

    scene, oid, cams, gt = synth
    with torch.no_grad():
        images, _, _ = scene.render(cams, backgrounds=torch.ones(len(cams), 3))
    data = SceneData(cameras=cams, images=images.clamp(0, 1), names=list(cams.names), train_ids=TRAIN,
                     test_ids=TEST, points=(scene.means, scene.base_colors), points_source="colmap")
    hook = GroupingHook(gt, 4, config=GroupConfig(reg_every=2), seed=0)
    w0 = hook.classifier.weight.detach().clone()
    groups = hook.parameters()
    assert groups[0]["params"][0] is hook.classifier.weight
    trainer = rec.Trainer(data, scene=scene, iters=16, hooks=[hook], identity_dim=16,
                          recipe=rec.Recipe(sh_degree=0, lr_identities=0.05), progress=False, seed=0,
                          strategy=DefaultStrategy(refine_start=10_000))
    ces = []
    for _ in range(16):
        trainer.train_step()
        ces.append(hook.last["ce"])
    out = trainer.final_scene()
    assert out.identities is not None and out.identities.shape == (len(scene), 16)
    assert not torch.equal(hook.classifier.weight.detach(), w0)
    assert np.mean(ces[-5:]) < 0.7 * np.mean(ces[:5])


def test_joint_grouping_of_a_run(tmp_path, synth):
    """`group --joint`: the run's capture is reconstructed again with the grouping hook."""
    rec = pytest.importorskip("ssgwarp.reconstruction.reconstruct")
    from ssgwarp.core.fileio import write_image, write_json
    from ssgwarp.grouping.stage import group_scene
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.raster.groups import load_groups
    from ssgwarp.formats.ply import read_ply

    scene, oid, cams, gt = synth
    with torch.no_grad():
        images, _, _ = scene.render(cams, backgrounds=torch.ones(len(cams), 3))
    c2w = cams.camtoworlds.double().numpy() @ np.diag([1.0, -1.0, -1.0, 1.0])   # OpenCV -> OpenGL axes
    frames = []
    for i, name in enumerate(cams.names):
        write_image(tmp_path / "data" / "images" / name, images[i].clamp(0, 1))
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w[i].tolist()})
    write_json(tmp_path / "data" / "transforms.json", {"camera_angle_x": 2 * math.atan(0.5), "frames": frames})
    recipe = rec.Recipe(init_max_points=300)
    rec.reconstruct(tmp_path / "data", tmp_path / "run",
                    rec.ReconstructConfig(iters=8, recipe=rec.Recipe(sh_degree=0, init_max_points=300)),
                    device="cpu", progress=False)
    info = group_scene(tmp_path / "run", joint=True, config=GroupConfig(dim=8),
                       reconstruct_kwargs={"iters": 8, "recipe": recipe}, progress=False)
    assert info["joint"] and info["joint_reconstruction"]["iters"] == 8
    grouped = read_ply(tmp_path / "run" / "scene.ply")
    assert grouped.identities is not None and grouped.identities.shape[1] == 8
    model = load_groups(tmp_path / "run")
    assert model.dim == 8 and model.num_groups == info["num_groups"] >= 2
    assert len(list((tmp_path / "run" / "groups" / "group_maps").iterdir())) == len(cams)


# -- real captures -------------------------------------------------------------------------------------------

def test_mask_free_on_real_capture(shared_data):
    """A points-based scene of LLFF fern: more than one group, and group maps that agree across views."""
    from ssgwarp.capture.datasets import load_dataset
    from ssgwarp.grouping.model import GroupConfig
    from ssgwarp.raster.groups import render_group_maps
    from ssgwarp.grouping.agreement import neighbour_pairs, reprojection_agreement
    from ssgwarp.grouping.train import train_identities
    from ssgwarp.grouping.pseudomasks import pseudo_masks

    data = load_dataset(shared_data / "llff_fern", images="images_8", width=48)
    xyz, rgb = data.points
    pick = torch.randperm(xyz.shape[0], generator=torch.Generator().manual_seed(0))[:1000]
    scene = GaussianScene.from_points(xyz[pick].float(), rgb[pick].float(), opacity=0.8)
    tc = data.cameras[data.train_ids]
    masks, res = pseudo_masks(scene, tc, seed=0)
    assert 1 < res.num_groups <= 8
    grouped, clf, _ = train_identities(scene, tc, masks, res.num_groups, config=GroupConfig(iters=30),
                                       progress=False)
    labels, _ = render_group_maps(grouped, data.cameras, clf)
    assert len(torch.unique(labels)) > 1
    agree = reprojection_agreement(grouped, data.cameras, labels, neighbour_pairs(data.cameras))
    print(f"fern (1000 points, 48x36): K={res.num_groups}, criterion {res.criterion['values']}, "
          f"reprojection agreement {agree['mean']:.4f} over {agree['pixels']} pixels")
    assert agree["pixels"] > 1000 and agree["mean"] > 0.85


# -- K when the neighbour graph falls apart (issue 38) ----------------------------------------------

def _feature_blobs(centres, n: int = 60, std: float = 0.2, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.tensor(c, dtype=torch.float64) + torch.randn(n, 2, generator=g, dtype=torch.float64) * std
                      for c in centres])


def _labels_of(xs, *, num_groups=None, cap=8, config=None, seed=0):
    from ssgwarp.grouping.pseudomasks import ClusterConfig, _spectral_labels, affinity_graph

    config = config or ClusterConfig()
    w = affinity_graph(xs, config.graph_k, config.sigma_rank)
    crit: dict = {}
    k, lab = _spectral_labels(xs, w, num_groups, cap, config, torch.Generator().manual_seed(seed), crit)
    return k, lab, crit, w


def _purity(lab: torch.Tensor, truth: torch.Tensor) -> float:
    k = int(max(lab.max(), truth.max())) + 1
    table = torch.zeros(k, k, dtype=torch.long).index_put_((lab, truth), torch.ones_like(lab), accumulate=True)
    return float(table.max(dim=1).values.sum()) / lab.numel()


def test_connected_components_of_a_graph():
    from ssgwarp.grouping.pseudomasks import connected_components

    w = torch.zeros(7, 7, dtype=torch.float64)
    for a, b in [(0, 3), (3, 5), (1, 2), (4, 6), (6, 4)]:
        w[a, b] = 0.5                                   # one-sided edges count as edges
    assert connected_components(w).tolist() == [0, 1, 1, 0, 2, 0, 2]
    assert connected_components(torch.zeros(3, 3)).tolist() == [0, 1, 2]
    assert connected_components(torch.ones(4, 4)).tolist() == [0, 0, 0, 0]


def test_a_graph_in_pieces_still_finds_the_clusters_inside_them():
    """The demo's failure (issue 38), in feature space: four touching clusters and one far away. The kNN graph
    has two components, so the Laplacian has two exact zeros and the log-eigengap after them is decided by its
    floor alone: the old rule took K = 2. Components first, then the pooled eigengap, finds all five."""
    from ssgwarp.grouping.pseudomasks import ClusterConfig, _best, _log_gaps, connected_components, spectral_embedding

    xs = _feature_blobs([(0, 0), (1, 0), (0, 1), (1, 1), (6, 6)])
    truth = torch.arange(5).repeat_interleave(60)
    cfg = ClusterConfig(graph_k=10)
    k, lab, crit, w = _labels_of(xs, config=cfg)
    assert sorted(torch.bincount(connected_components(w)).tolist()) == [60, 240]
    evals = spectral_embedding(w, 9)[0]
    assert float(evals[1]) < 1e-9 and _best(_log_gaps(evals, 2, 8, ClusterConfig().gap_floor), 1) == 2  # the old rule
    assert k == 5 and crit["components"] == [240, 60] and crit["measure"].startswith("eigengap")
    assert max(crit["values"], key=crit["values"].get) == 5 and crit["fragments"] == 0
    assert _purity(lab, truth) >= 0.95 and len(set(lab[truth == 4].tolist())) == 1
    # deterministic: the same labels again
    assert torch.equal(lab, _labels_of(xs, config=cfg)[1])


def test_components_as_groups_caps_and_given_k():
    xs = _feature_blobs([(0, 0), (5, 0), (0, 5), (5, 5), (10, 10)], std=0.1)
    truth = torch.arange(5).repeat_interleave(60)
    k, lab, crit, _ = _labels_of(xs)
    # five compact, separate blobs: the components are the groups (no split of a blob)
    assert k == 5 and crit["components"] == [60] * 5 and _purity(lab, truth) == 1.0
    assert crit["values"][5] == max(crit["values"].values())
    # a given K above the components splits the components that own the smallest eigenvalues; below, the
    # components are kept (the caller merges them down to K by their centroids)
    k7, lab7, _, _ = _labels_of(xs, num_groups=7)
    assert k7 == 7 and len(lab7.unique()) == 7
    k3, lab3, _, _ = _labels_of(xs, num_groups=3)
    assert k3 == 5 and torch.equal(lab3, lab)


def test_cluster_gaussians_merges_components_down_to_the_cap_and_votes_fragments_in():
    from ssgwarp.grouping.pseudomasks import ClusterConfig, cluster_gaussians

    # five separate blobs of Gaussians far apart, no cameras: more components than a cap of 3
    xyz = _feature_blobs([(0, 0), (3, 0), (0, 3), (3, 3), (6, 6)], n=40, std=0.05).float()
    xyz = torch.cat([xyz, torch.zeros(len(xyz), 1)], 1)
    n = len(xyz)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    scene = GaussianScene(xyz, torch.full((n, 3), math.log(0.05)), quats, torch.full((n,), 3.0),
                          rgb_to_sh_dc(torch.full((n, 3), 0.5)))
    res = cluster_gaussians(scene, config=ClusterConfig(max_groups=3, weights=(1.0, 1.0, 0.1)), seed=0)
    assert res.num_groups == 3 and res.criterion["components"] == [40] * 5 and len(res.criterion["merged"]) == 2
    free = cluster_gaussians(scene, config=ClusterConfig(weights=(1.0, 1.0, 0.1)), seed=0)
    assert free.num_groups == 5 and not free.criterion["merged"]
    truth = torch.arange(5).repeat_interleave(40)
    assert _purity(free.labels, truth) == 1.0
    # a piece too small to be a group (under min_fraction of the sample) is not one: it joins a group
    cfg = ClusterConfig(weights=(1.0, 1.0, 0.1), graph_k=5, sigma_rank=3, min_fraction=0.1)
    res = cluster_gaussians(scene.subset(torch.arange(n - 32)), config=cfg, seed=0)     # the last blob: 8 left
    assert res.criterion["fragments"] == 8 and any(m.get("fragment") for m in res.criterion["merged"])
    frag = res.labels[n - 40:n - 32]
    assert bool(torch.isin(frag, res.labels[:n - 40]).all())          # in groups of the other blobs' Gaussians
