"""Stage 2: crops, model-coordinate targets, symmetry-aware loss, RANSAC poses, the crop network and its training."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from argen.cli.app import app as argen_app
from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, run_label
from detector.stage2.network import CropNet, CropNetConfig, EdgeConv, _NeighbourMax, crop_loss, knn
from detector.stage2.crops import (
    CropConfig,
    PartTurns,
    ball_rows,
    crop_input,
    crop_region,
    jittered_centre,
    model_coordinates,
    negative_crop,
    negative_reach,
    roll_about_ray,
    symmetry_targets,
    training_crop,
)
from detector.data.augment import NORMALISATION, input_normalisation
from detector.errors import DetectorError
from detector.geometry.kabsch import kabsch_batch, ransac_kabsch
from detector.stage2.dataset import CropDataset, collate_crops, crop_symmetries, part_turns
from detector.stage2.train import load_stage2_config


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    """A 4-frame noisy capture-sim dataset of the built-in objects, labelled; no distractors on the board and the
    objects apart, so that each shows enough points for the crop tests."""
    d = tmp_path_factory.mktemp("crops")
    r = CliRunner().invoke(argen_app, ["capture-sim", "--frames", "4", "--out", str(d / "ds"), "--seed", "8",
                                       "--set", "clutter.on_board=[0,0]", "--set", "placement.beside=0", "--quiet"])
    assert r.exit_code == 0, r.output
    run_label(LabelRequest(dataset=d / "ds", split="train_pbr", out=d / "l.h5", progress=False,
                           cfg=LabelConfig(max_points=20000)))
    return d / "l.h5"


def test_training_crop_targets_are_the_instance_and_its_model_coordinates(labels):
    cfg = CropConfig(centre_jitter=0.0)
    with LabelFile(labels) as lf:
        tab = lf.objects
        f = lf.frame(0)
        xyz = f.features[:, :3].astype(np.float64)
        for g in range(len(f.instances)):
            m = tab.index(int(f.instances.obj_id[g]))
            dia = float(tab.diameters[m])
            if f.instances.num_points[g] < cfg.min_object_points:  # CropDataset leaves these out too
                continue
            c = training_crop(f, g, dia, tab.sym_transforms[m], cfg, np.random.default_rng(0), NORMALISATION)
            if c is None:
                continue
            centre = f.instances.control_points[g][8]
            # input: points relative to the (unjittered) centre in radii, all inside the ball
            assert np.abs(c["centre"] - centre).max() < 1e-6
            assert np.linalg.norm(c["features"][:, :3], axis=1).max() <= 1.0 + 1e-5
            p = c["features"][:, :3] * cfg.radius * dia + centre
            fg = c["fg"] > 0
            assert fg.any() and not fg.all()
            # foreground: exactly the points the label file gives to this instance
            d, j = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(xyz).query(p)
            assert d.max() < 1e-5
            assert np.array_equal(fg, f.instance[j] == g)
            # identity symmetry first: R @ (coords * dia) + t reproduces the camera points
            back = (c["coords"][0] * dia) @ f.instances.R[g].T + f.instances.t[g]
            assert np.abs(back - p).max() < 1e-4
            # foreground points lie on the model: near the model's surface sample
            near = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(tab.model_points[m]).query(
                c["coords"][0][fg] * dia)[0]
            assert np.median(near) < 0.01


def test_neighbour_copy_is_the_instance_moved_across_the_ray_and_upright():
    from detector.stage2.crops import add_neighbour

    rng = np.random.default_rng(11)
    centre = np.array([0.1, -0.05, 0.8])
    pts = centre + rng.normal(scale=0.03, size=(200, 3))
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    feats = np.concatenate([pts, rng.random((200, 3)), normals], 1).astype(np.float32)
    ray = centre / np.linalg.norm(centre)
    for _ in range(10):
        p, f = add_neighbour(np.concatenate([pts, centre[None]]), np.concatenate([feats, feats[:1]]), centre, 0.1,
                             (0.5, 0.8), rng)
        move = p[-1] - centre  # where the instance's centre went: across the ray, 0.5-0.8 diameters
        assert abs(move @ ray) < 1e-9 and 0.05 - 1e-9 <= np.linalg.norm(move) <= 0.08 + 1e-9
        # a rigid motion turning about the ray by at most 30 degrees: distances kept, normals turned alike
        assert np.allclose(np.linalg.norm(p[:-1] - p[-1], axis=1), np.linalg.norm(pts - centre, axis=1))
        Q = np.linalg.lstsq(pts - centre, p[:-1] - p[-1], rcond=None)[0].T
        assert np.allclose(Q @ ray, ray, atol=1e-6) and np.degrees(np.arccos((np.trace(Q) - 1) / 2)) <= 30.0 + 1e-6
        assert np.allclose(f[:-1, 6:9], normals @ Q.T, atol=1e-5) and np.allclose(f[:, :3], p, atol=1e-6)
        assert np.array_equal(f[:, 3:6], np.concatenate([feats, feats[:1]])[:, 3:6])


def test_training_crops_with_a_neighbour_copy_keep_their_targets(labels):
    """With the neighbour augmentation on every crop, the foreground is still exactly the instance's points with
    their model coordinates, and the crops hold more background (the copy) than without it."""
    from scipy.spatial import cKDTree

    with LabelFile(labels) as lf:
        tab, f = lf.objects, lf.frame(1)
        share = {}
        for chance in (0.0, 1.0):
            cfg = CropConfig(neighbour=chance, neighbour_offset=(0.5, 0.7), roll_deg=0.0)
            fgs = []
            for g in range(len(f.instances)):
                m = tab.index(int(f.instances.obj_id[g]))
                dia = float(tab.diameters[m])
                for seed in range(4):
                    c = training_crop(f, g, dia, tab.sym_transforms[m], cfg, np.random.default_rng(seed),
                                      NORMALISATION, augment=True)
                    p = c["features"][:, :3] * cfg.radius * dia + c["centre"]
                    fg = c["fg"] > 0
                    back = (c["coords"][0][fg] * dia) @ f.instances.R[g].T + f.instances.t[g]
                    assert np.abs(back - p[fg]).max() < 0.006  # the points carry 1 mm noise
                    own = f.features[f.instance == g, :3]
                    assert np.median(cKDTree(own).query(p[fg])[0]) < 0.003
                    fgs.append(fg.mean())
            share[chance] = np.mean(fgs)
    assert share[1.0] < 0.9 * share[0.0], share


def largest_instance(lf):
    """Frame 0 of an open label file, its instance with the most labelled points, and training_crop's first four
    arguments for it: (frame, g, args)."""
    tab, f = lf.objects, lf.frame(0)
    g = int(np.argmax(f.instances.num_points))
    m = tab.index(int(f.instances.obj_id[g]))
    return f, g, (f, g, float(tab.diameters[m]), tab.sym_transforms[m])


def test_camera_colour_augmentation_spans_real_camera_changes(labels):
    """The "camera" colour augmentation: seeded, in [0, 1], exposure below 0.7 and above 1.3 both drawn, some crops
    grey and some without colour; a training crop with it keeps the points and targets of the geometry."""
    from detector.data.augment import camera_colour

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 0.8, (200, 3)).astype(np.float32)
    draws = [camera_colour(rgb, np.random.default_rng(k)) for k in range(300)]
    assert np.array_equal(draws[7], camera_colour(rgb, np.random.default_rng(7)))
    assert all(d.dtype == np.float32 and d.shape == rgb.shape and d.min() >= 0 and d.max() <= 1 for d in draws)
    ratio = np.array([d.mean() / rgb.mean() for d in draws])
    assert (ratio < 0.7).sum() > 10 and (ratio > 1.3).sum() > 10
    zeros = sum(not d.any() for d in draws)
    grey = sum(d.any() and np.abs(d - d.mean(1, keepdims=True)).max() < 0.1 for d in draws)
    assert 3 <= zeros <= 30 and 10 <= grey <= 60
    with LabelFile(labels) as lf:
        f, g, args = largest_instance(lf)
        plain = training_crop(*args, CropConfig(roll_deg=0.0), np.random.default_rng(3), NORMALISATION, augment=True)
        cam = training_crop(*args, CropConfig(roll_deg=0.0, colour="camera"), np.random.default_rng(3), NORMALISATION,
                            augment=True)
    assert np.array_equal(plain["fg"], cam["fg"]) and np.array_equal(plain["coords"], cam["coords"])
    assert not np.allclose(plain["features"][:, 3:6], cam["features"][:, 3:6])


def test_camera_tone_changes_contrast_and_saturation_and_keeps_the_targets(labels):
    """"camera_tone": the "camera" draws (the same exposure, white balance and gamma under the same seed: without
    the tone curve the colours are "camera"'s bit for bit) followed by contrast and saturation gains: across seeds
    both less and more saturated and contrasted crops than "camera" gives, more clipped channels, colours in [0, 1];
    a training crop with it keeps the points and targets."""
    from detector.data.augment import camera_colour

    rgb = np.random.default_rng(0).uniform(0.15, 0.85, (300, 3)).astype(np.float32)
    sat, con, clipped = [], [], [0, 0]
    for k in range(200):
        cam, tone = camera_colour(rgb, np.random.default_rng(k)), camera_colour(rgb, np.random.default_rng(k), True)
        assert tone.dtype == np.float32 and tone.min() >= 0 and tone.max() <= 1
        assert np.array_equal(cam, camera_colour(rgb, np.random.default_rng(k), False))
        if not cam.any():  # a depth-only draw stays one
            assert not tone.any()
            continue
        if np.abs(cam - cam.mean(1, keepdims=True)).max() < 0.1:
            continue  # grey: saturation cannot change it
        spread = lambda c: np.abs(c - c.mean(1, keepdims=True)).mean()
        sat.append(spread(tone) / spread(cam))
        con.append(tone.mean(1).std() / cam.mean(1).std())
        clipped[0] += int((cam >= 0.98).sum())
        clipped[1] += int((tone >= 0.98).sum())
    assert min(sat) < 0.8 and max(sat) > 1.4 and min(con) < 0.85 and max(con) > 1.3
    assert clipped[1] > clipped[0]
    with LabelFile(labels) as lf:
        f, g, args = largest_instance(lf)
        cam = training_crop(*args, CropConfig(roll_deg=0.0, colour="camera"), np.random.default_rng(3), NORMALISATION,
                            augment=True)
        tone = training_crop(*args, CropConfig(roll_deg=0.0, colour="camera_tone"), np.random.default_rng(3),
                             NORMALISATION, augment=True)
    assert np.array_equal(cam["fg"], tone["fg"]) and np.array_equal(cam["coords"], tone["coords"])
    np.testing.assert_array_equal(cam["features"][:, [0, 1, 2, 6, 7, 8]], tone["features"][:, [0, 1, 2, 6, 7, 8]])


def test_colour_none_crops_have_no_colour_and_the_same_targets(labels):
    """Stage 2 without colour input: a training crop's colour channels are zero, its points, normals and targets are
    the colour crop's (the crop draws no colour change), and the poser's crop input is zero there too."""
    none = input_normalisation("none")
    with LabelFile(labels) as lf:
        f, g, args = largest_instance(lf)
        rgb = training_crop(*args, CropConfig(roll_deg=0.0, colour="none"), np.random.default_rng(3), NORMALISATION,
                            augment=True)
        bare = training_crop(*args, CropConfig(roll_deg=0.0, colour="none"), np.random.default_rng(3), none,
                             augment=True)
        rows = np.flatnonzero(np.asarray(f.instance) == g)[:50]
        inp = crop_input(np.asarray(f.features, np.float32), rows, f.features[rows[0], :3], 0.05, none)
    assert not np.any(bare["features"][:, 3:6]) and np.any(rgb["features"][:, 3:6])
    assert np.array_equal(rgb["features"][:, [0, 1, 2, 6, 7, 8]], bare["features"][:, [0, 1, 2, 6, 7, 8]])
    assert np.array_equal(rgb["fg"], bare["fg"]) and np.array_equal(rgb["coords"], bare["coords"])
    assert not np.any(inp[:, 3:6]) and np.any(inp[:, :3])


def test_colour_ranks_ignore_any_increasing_change_of_a_channel():
    """colour_ranks: each channel's rank among the points, zero mean and unit variance; equal values share a rank;
    an increasing change of each channel (gain, white balance, gamma, an offset) leaves it bit for bit the same,
    a change of the colours' order (another colour at some points) does not."""
    from detector.data.augment import colour_ranks

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.05, 0.7, (256, 3))
    r = colour_ranks(rgb)
    assert r.dtype == np.float32 and r.shape == rgb.shape
    np.testing.assert_allclose(r.mean(0), 0.0, atol=1e-6)
    np.testing.assert_allclose(r.std(0), 1.0, atol=1e-3)
    changed = (rgb * np.array([1.3, 0.9, 1.1])) ** np.array([0.6, 1.0, 1.5]) + 0.02
    np.testing.assert_array_equal(colour_ranks(changed), r)
    other = rgb.copy()
    other[:20] = other[20:40, ::-1]
    assert not np.array_equal(colour_ranks(other), r)
    ties = colour_ranks(np.array([[0.2, 1.0, 0.5], [0.9, 1.0, 0.5], [0.4, 1.0, 0.5]]))
    np.testing.assert_allclose(ties[:, 0], np.array([-1.0, 1.0, 0.0]) * np.sqrt(12) / 3, rtol=1e-6)
    assert not np.any(ties[:, 1:]) and colour_ranks(np.zeros((0, 3))).shape == (0, 3)


def test_grey_world_balances_each_channel_and_ignores_gains():
    """grey_world: each channel scaled to a mean of 0.5, so any per-channel gain (exposure, white balance) gives the
    same output; the ratio of two points' colours is kept; values clip at 2; a dark channel gives 0."""
    from detector.data.augment import grey_world

    rgb = np.random.default_rng(1).uniform(0.05, 0.6, (300, 3))
    out = grey_world(rgb)
    np.testing.assert_allclose(out.mean(0), 0.5)
    np.testing.assert_allclose(grey_world(rgb * np.array([1.4, 0.8, 0.5])), out)
    np.testing.assert_allclose(out[0] / out[1], rgb[0] / rgb[1])
    spike = rgb.copy()
    spike[0, 0] = 300 * spike[:, 0].mean()
    assert grey_world(spike)[0, 0] == 2.0
    dark = rgb.copy()
    dark[:, 2] = 0.0
    assert not np.any(grey_world(dark)[:, 2]) and grey_world(np.zeros((0, 3))).shape == (0, 3)


def test_rank_crops_are_the_same_under_another_cameras_colours_and_keep_the_targets(labels):
    """Stage 2 with colour ranks ("rank"): the poser's input of a crop is the same when the frame's colours come
    from a camera with another exposure, white balance and gamma; a training crop keeps the points and targets of
    "camera_tone" (the same draws) and its colour channels are the ranks of the changed colours."""
    from detector.data.augment import camera_colour, colour_ranks

    rank = input_normalisation("rank")
    assert rank["colour"] == "rank"
    with LabelFile(labels) as lf:
        f, g, args = largest_instance(lf)
        tone = training_crop(*args, CropConfig(roll_deg=0.0, colour="camera_tone"), np.random.default_rng(3),
                             NORMALISATION, augment=True)
        ranked = training_crop(*args, CropConfig(roll_deg=0.0, colour="rank"), np.random.default_rng(3), rank,
                               augment=True)
        feats = np.asarray(f.features, np.float32)
        rows = np.flatnonzero(np.linalg.norm(feats[:, :3] - feats[np.asarray(f.instance) == g, :3].mean(0), axis=1)
                              < 0.08)
        other = feats.copy()
        other[:, 3:6] = (feats[:, 3:6] * np.array([0.7, 0.6, 0.8], np.float32)) ** np.float32(1.4)
        a = crop_input(feats, rows, feats[rows, :3].mean(0), 0.08, rank)
        b = crop_input(other, rows, feats[rows, :3].mean(0), 0.08, rank)
    assert len(rows) > 50 and len(np.unique(feats[rows, 3])) > 10
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(crop_input(feats, rows, feats[rows, :3].mean(0), 0.08, NORMALISATION)[:, 3:6],
                           crop_input(other, rows, feats[rows, :3].mean(0), 0.08, NORMALISATION)[:, 3:6])
    assert np.array_equal(tone["fg"], ranked["fg"]) and np.array_equal(tone["coords"], ranked["coords"])
    np.testing.assert_array_equal(tone["features"][:, [0, 1, 2, 6, 7, 8]], ranked["features"][:, [0, 1, 2, 6, 7, 8]])
    rgb = tone["features"][:, 3:6] * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]  # "camera_tone"'s colours
    np.testing.assert_allclose(ranked["features"][:, 3:6], colour_ranks(rgb), atol=1e-5)


def test_symmetry_targets_are_the_coordinates_under_each_equivalent_pose():
    rng = np.random.default_rng(0)
    S = np.tile(np.eye(4), (2, 1, 1))
    S[1, :3, :3] = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    S[1, :3, 3] = [0.01, 0.0, 0.0]
    R, t, dia = Rotation.random(random_state=rng).as_matrix(), np.array([0.0, 0.1, 0.8]), 0.2
    x = rng.normal(size=(50, 3)) * 0.05
    p = x @ R.T + t
    tg = symmetry_targets(model_coordinates(p, R, t, dia), S, dia)
    assert np.allclose(tg[0] * dia, x, atol=1e-6)
    # under the equivalent pose T @ S the same camera points have the coordinates tg[1]
    R2, t2 = R @ S[1, :3, :3], R @ S[1, :3, 3] + t
    assert np.allclose((tg[1] * dia) @ R2.T + t2, p, atol=1e-6)


def test_crop_centre_jitter_scales_with_the_diameter_and_is_clipped():
    cfg = CropConfig(centre_jitter=0.1, centre_jitter_clip=0.25)
    c = np.array([0.1, -0.2, 0.9])
    for dia in (0.1, 0.26):
        rng = np.random.default_rng(5)
        off = np.array([jittered_centre(c, dia, cfg, rng) for _ in range(4000)]) - c
        assert np.allclose(off.std(0), 0.1 * dia, rtol=0.08)  # a larger object gets a larger centre error
        assert np.abs(off).max() <= 0.25 * dia + 1e-12
        assert np.abs(off).max() > 0.2 * dia  # the clip is reached, not far beyond the tail


def test_ball_rows_are_the_points_within_the_radius():
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(5000, 3)) * 0.2 + [0, 0, 1.0]
    centre = np.array([0.05, -0.02, 1.01])
    xyz[:40] = centre + rng.normal(size=(40, 3)) * [0, 0, 1] * 0.1  # on the centre's line of sight: dz is all of it
    xyz[40] = centre + [0, 0, 0.1]  # exactly on the sphere
    for radius in (0.05, 0.1, 0.3):
        brute = np.flatnonzero(np.sum((xyz - centre) ** 2, axis=1) <= radius * radius)
        assert np.array_equal(ball_rows(xyz, centre, radius), brute)


def test_stage2_trains_in_bfloat16_close_to_float32_and_lowers_the_loss(labels):
    """``stage2.net_dtype`` bfloat16: a batch's loss and its gradients within bfloat16's rounding of float32's, the
    weights stay float32, and a few steps lower the loss as in float32; a run saved before the setting resumes as
    float32; another format is a config error."""
    from detector.stage2.train import forward_stage2_loss, saved_settings

    ds = CropDataset(labels, CropConfig(num_points=128), augment=True, seed=0)
    batch = collate_crops([ds[(0, i)] for i in range(len(ds))])
    f32, b16 = load_stage2_config(None), load_stage2_config(None, {"net_dtype": "bfloat16"})
    torch.manual_seed(0)
    net = CropNet(CropNetConfig(width=32, edge_width=32, global_width=64, head_width=64, k=8), len(ds.class_ids))
    grads = []
    for cfg in (f32, b16):
        net.zero_grad()
        loss, parts = forward_stage2_loss(net, batch, cfg, torch.device("cpu"))
        loss.backward()
        assert loss.dtype == torch.float32
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
        if cfg is f32:
            ref = float(loss.detach())
    assert abs(float(loss.detach()) - ref) < 0.02 * ref and float(loss.detach()) != ref
    assert all(p.dtype == torch.float32 and p.grad.dtype == torch.float32 for p in net.parameters())
    cos = torch.nn.functional.cosine_similarity(grads[0], grads[1], dim=0)
    assert cos > 0.99, float(cos)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss, _ = forward_stage2_loss(net, batch, b16, torch.device("cpu"))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]
    assert saved_settings({"steps": 3})["net_dtype"] == "float32"
    with pytest.raises(DetectorError, match="net_dtype must be float32 or bfloat16"):
        load_stage2_config(None, {"net_dtype": "float16"})


def test_knn_finds_the_same_neighbours_in_training_and_at_inference():
    torch.manual_seed(1)
    xyz = torch.randn(3, 40, 3)
    idx = knn(xyz, 6)  # training: nearest first
    d = torch.cdist(xyz, xyz)
    assert torch.equal(idx[..., 0], torch.arange(40).expand(3, 40))  # each point is its own nearest
    assert torch.all(d.gather(-1, idx).diff(dim=-1) >= 0)
    with torch.no_grad():  # inference: the same sets, in an order the running maximum does not depend on
        assert torch.equal(knn(xyz, 6).sort(-1).values, idx.sort(-1).values)


def test_edge_convolution_equals_its_definition_per_point():
    torch.manual_seed(0)
    conv = EdgeConv(5, 7)
    x, idx = torch.randn(2, 9, 5), torch.randint(0, 9, (2, 9, 4))
    out = conv(x, idx)
    with torch.no_grad():  # inference takes the running-maximum path: the same values
        assert torch.allclose(conv(x, idx), out, atol=1e-6)
    W1, b1, W2 = conv.self_lin.weight, conv.self_lin.bias, conv.nb_lin.weight
    for bi in range(2):
        for i in range(9):
            edges = torch.stack([W1 @ x[bi, i] + b1 + W2 @ (x[bi, j] - x[bi, i]) for j in idx[bi, i]])  # (k, 7)
            assert torch.allclose(out[bi, i], torch.relu(conv.norm(edges.max(0).values)), atol=1e-5)
    # model files store the option that chose this design (checkpoints/lm8.pt); the other design is refused
    assert CropNetConfig.from_dict({**CropNetConfig().to_dict(), "norm_before_max": False}) == CropNetConfig()
    with pytest.raises(DetectorError, match="norm_before_max"):
        CropNetConfig.from_dict({**CropNetConfig().to_dict(), "norm_before_max": True})
    # a stage-2 run started when the option existed resumes: its saved settings name this network
    from detector.stage2.train import saved_settings

    # (and one started before narrow_steps trained its stages one after the other: 0)
    assert saved_settings({"net": {"k": 12, "norm_before_max": False}, "steps": 3}) == \
        {"net": {"k": 12}, "steps": 3, "narrow_steps": 0, "net_dtype": "float32"}
    # one started before part symmetries is resumed without them; a new run has them
    assert saved_settings({"crop": {"colour": "none"}})["crop"]["part_turns"] is False
    assert CropConfig().part_turns is True


def test_crop_network_head_is_one_layer_on_the_points_and_the_global_feature():
    """The head's first layer takes the global feature once a crop: the same outputs, and gradients, as that layer on
    each point's [local, global] row (the network as it trained before)."""
    torch.manual_seed(2)
    net = CropNet(CropNetConfig(width=16, edge_width=24, global_width=20, head_width=32, k=5), 3)
    feats, cls = torch.randn(4, 30, 9), torch.tensor([0, 2, 1, 2])

    def concatenated(f, c):  # the forward with the global feature written out beside every point
        n = f.shape[1]
        x0 = net.point(torch.cat([f, torch.nn.functional.one_hot(c, 3).float()[:, None].expand(-1, n, -1)], -1))
        idx = knn(f[..., :3], net.cfg.k)
        x1 = net.edge1(x0, idx)
        local = torch.cat([x0, x1, net.edge2(x1, idx)], -1)
        g = net.glob(local).max(dim=1).values
        out = net.head(torch.cat([local, g[:, None].expand(-1, n, -1)], -1)).reshape(4, n, 3, 4)
        return out[torch.arange(4), :, c]

    out, ref = net(feats, cls), concatenated(feats, cls)
    torch.testing.assert_close(out["fg_logit"], ref[..., 0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["coords"], ref[..., 1:], atol=1e-5, rtol=1e-5)
    w = net.head[0][0].weight
    g1 = torch.autograd.grad(out["coords"].square().sum() + out["fg_logit"].sum(), w)[0]
    g2 = torch.autograd.grad(ref[..., 1:].square().sum() + ref[..., 0].sum(), w)[0]
    torch.testing.assert_close(g1, g2, atol=1e-5, rtol=1e-4)


def test_roll_about_the_ray_keeps_the_centre_and_model_coordinates():
    rng = np.random.default_rng(1)
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.1, -0.05, 0.9])
    x = rng.normal(size=(40, 3)) * 0.05
    p = x @ R.T + t
    q, Q = roll_about_ray(p, t, 0.7)
    assert np.allclose(Q @ t / np.linalg.norm(t), t / np.linalg.norm(t))  # the ray is the axis
    # the rolled points are the same model points under the rolled pose
    assert np.allclose(model_coordinates(q, Q @ R, Q @ (t - t) + t, 1.0), x, atol=1e-6)


def test_a_rolled_crop_input_is_the_crop_of_the_rolled_points():
    """roll_crop_input turns a crop's positions and normals as roll_about_ray turns the frame's points (training's
    roll), and keeps its colours."""
    from detector.stage2.crops import roll_crop_input

    rng = np.random.default_rng(3)
    c, radius = np.array([0.08, -0.03, 0.85]), 0.07
    feats = np.zeros((300, 9), np.float32)
    feats[:, :3] = c + rng.normal(0, 0.03, (300, 3))
    feats[:, 3:6] = rng.random((300, 3))
    n = rng.normal(size=(300, 3))
    feats[:, 6:9] = n / np.linalg.norm(n, axis=1, keepdims=True)
    rows = np.arange(0, 300, 2)
    inp = crop_input(feats, rows, c, radius, NORMALISATION)
    assert roll_crop_input(inp, c, 0.0) is inp
    q, Q = roll_about_ray(feats[:, :3].astype(np.float64), c, 0.3)
    turned = feats.copy()
    turned[:, :3] = q
    turned[:, 6:9] = feats[:, 6:9] @ Q.T
    rolled = roll_crop_input(inp, c, 0.3)
    np.testing.assert_allclose(rolled, crop_input(turned, rows, c, radius, NORMALISATION), atol=1e-5)
    np.testing.assert_array_equal(rolled[:, 3:6], inp[:, 3:6])
    assert not np.allclose(rolled[:, :3], inp[:, :3], atol=1e-3)


def test_crop_subsets_are_rolled_apart_and_keep_their_points():
    """With infer.roll_deg, subset k of a crop reaches the network rolled by the k-th of angles spread evenly over
    [-roll_deg, roll_deg], the same points as without the roll; the predictions come back paired with the points'
    own rows (the model coordinates do not depend on the roll)."""
    from detector.stage2.crops import ray_roll, roll_crop_input
    from detector.stage2.poser import PoserConfig, crop_predictions, subset_rolls

    np.testing.assert_allclose(subset_rolls(3, 10.0), np.deg2rad([-10.0, 0.0, 10.0]))
    assert np.array_equal(subset_rolls(1, 10.0), [0.0]) and np.array_equal(subset_rolls(4, 0.0), np.zeros(4))
    with pytest.raises(DetectorError, match="roll_deg"):
        PoserConfig(roll_deg=120)

    class Recorder(torch.nn.Module):  # echoes each point's input position as its "model coordinates"
        def __init__(self):
            super().__init__()
            self.seen = []

        def forward(self, features, cls):
            self.seen.append(features.clone())
            return {"fg_logit": torch.zeros(features.shape[:2]), "coords": features[..., :3].clone()}

    rng = np.random.default_rng(9)
    centres, dia = np.array([[0.02, 0.05, 0.9], [-0.1, 0.0, 0.7]]), 0.1
    feats = np.zeros((6000, 9), np.float32)
    feats[:3000, :3] = centres[0] + rng.normal(0, 0.03, (3000, 3))
    feats[3000:, :3] = centres[1] + rng.normal(0, 0.03, (3000, 3))
    feats[:, 6:9] = [0.0, 0.0, -1.0]
    cfg = CropConfig(num_points=128)
    runs = {}
    for roll in (0.0, 12.0):
        net = Recorder()
        out = crop_predictions(net, feats, centres, np.array([0, 0]), np.array([dia, dia]), cfg, NORMALISATION,
                               seed=4, samples=3, roll_deg=roll)
        runs[roll] = (net.seen[0], out)
    (plain, out0), (rolled, out1) = runs[0.0], runs[12.0]
    angles = subset_rolls(3, 12.0)
    for d, c in enumerate(centres):  # the network's batch holds crop d's subsets at rows 3d, 3d + 1, 3d + 2
        rows0, rows1, coords1 = out0[d][0], out1[d][0], out1[d][2]
        assert np.array_equal(rows0, rows1)
        for k, angle in enumerate(angles):
            np.testing.assert_allclose(rolled[3 * d + k].numpy(), roll_crop_input(plain[3 * d + k].numpy(), c, angle),
                                       atol=1e-6)
            # the echoed (rolled) positions come back beside the rows they were cut from
            sub = slice(128 * k, 128 * (k + 1))
            Q = ray_roll(c, angle)
            back = (feats[rows1[sub], :3] - c) / (cfg.radius * dia)
            np.testing.assert_allclose(coords1[sub] / dia, back @ Q.T, atol=1e-5)


def test_ransac_kabsch_recovers_a_pose_with_half_outliers():
    rng = np.random.default_rng(2)
    for _ in range(5):
        R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        m = rng.normal(size=(200, 3)) * 0.05
        p = m @ R.T + t + rng.normal(0, 0.001, (200, 3))
        bad = rng.random(200) < 0.5
        p[bad] = t + rng.normal(size=(bad.sum(), 3)) * 0.05
        Re, te, inl = ransac_kabsch(m, p, np.ones(200), 0.01, rng)
        assert np.degrees(np.arccos(np.clip((np.trace(Re.T @ R) - 1) / 2, -1, 1))) < 1.0
        assert np.linalg.norm(te - t) < 0.002
        assert np.array_equal(inl, ~bad)
    Rb, tb = kabsch_batch(m[None, :3].repeat(4, 0), p[None, :3].repeat(4, 0))
    assert np.allclose(np.linalg.det(Rb), 1.0)


def test_ransac_keeps_hypotheses_without_inliers_beside_good_ones():
    """keep > the hypotheses with inliers: those with none keep their 3-point pose (they once made a zero-weight
    refit whose NaN failed the whole batch's SVD, seen on a real crop)."""
    rng = np.random.default_rng(7)
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
    m = rng.normal(size=(50, 3)) * 0.05
    p = m @ R.T + t
    p[20:] = t + rng.normal(size=(30, 3)) * 0.05  # 30 of 50 correspondences wrong: most hypotheses have none
    out = ransac_kabsch(m, p, np.ones(50), 1e-4, rng, hypotheses=128, keep=32)
    assert len(out) == 32 and all(np.isfinite(Rk).all() and np.isfinite(tk).all() for Rk, tk, _ in out)
    Rb, tb, inl = out[0]
    assert np.allclose(Rb, R, atol=1e-6) and np.allclose(tb, t, atol=1e-6) and inl[:20].all()
    assert any(k[2].sum() < 3 for k in out)  # the case this test is about did occur


def test_batched_kabsch_and_fit_measure_equal_their_one_at_a_time_forms():
    """The vectorised refits (weighted_kabsch_shared) and the K-pose fit_residuals give what kabsch and
    fit_residuals give one weighting / one pose at a time, reflections excluded."""
    from scipy.spatial import cKDTree

    from detector.geometry.icp import fit_residuals
    from detector.geometry.kabsch import kabsch, weighted_kabsch_shared

    rng = np.random.default_rng(4)
    m = rng.normal(size=(60, 3)) * 0.05
    R, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
    p = m @ R.T + t + rng.normal(0, 0.002, m.shape)
    W = rng.uniform(0, 1, (6, 60)) * (rng.random((6, 60)) < 0.7)
    Rb, tb = weighted_kabsch_shared(m, p, W)
    for k in range(6):
        on = W[k] > 0
        Rk, tk = kabsch(m[on], p[on], W[k, on])
        assert np.abs(Rk - Rb[k]).max() < 1e-9 and np.abs(tk - tb[k]).max() < 1e-9
    assert np.allclose(np.linalg.det(Rb), 1.0)
    mirrored = weighted_kabsch_shared(m, p * [1, 1, -1], W[:1])[0][0]  # a mirror image is still fitted by a rotation
    assert np.linalg.det(mirrored) == pytest.approx(1.0)
    tree, normals = cKDTree(m), rng.normal(size=m.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    poses = [Rotation.random(random_state=rng).as_matrix() for _ in range(4)]
    shifts = rng.normal(size=(4, 3)) * 0.01
    many = fit_residuals(p, tree, normals, np.stack(poses), shifts + t, 0.01)
    for k in range(4):
        assert np.allclose(many[k], fit_residuals(p, tree, normals, poses[k], shifts[k] + t, 0.01), atol=1e-12)


def test_crop_loss_takes_the_best_symmetry_and_ignores_padding():
    torch.manual_seed(0)
    coords = torch.randn(2, 3, 10, 3)
    fg = torch.ones(2, 10)
    mask = torch.tensor([[True, True, False], [True, False, False]])
    out = {"fg_logit": torch.full((2, 10), 20.0), "coords": coords[:, 1].clone()}
    out["coords"][1] = coords[1, 0]  # crop 1 predicts its only real symmetry exactly
    _, parts = crop_loss(out, fg, coords, mask)
    assert parts["coord"] < 1e-6  # crop 0 matches its 2nd symmetry, crop 1 its 1st
    out["coords"][0] = coords[0, 2]  # the padded 3rd symmetry does not count
    _, parts = crop_loss(out, fg, coords, mask)
    assert parts["coord"] > 0.1


def test_training_neighbour_max_has_the_gather_and_max_values_and_gradients():
    # the training path's running maximum against the plain (M, k, C) gather and max, ties included
    torch.manual_seed(0)
    b = torch.randn(40, 6, dtype=torch.float64)
    b[7] = b[3]  # two rows with equal features: ties between neighbours
    rows = torch.randint(0, 40, (25, 5))
    rows[0] = torch.tensor([3, 7, 3, 7, 1])
    w = torch.randn(25, 6, dtype=torch.float64)
    b1, b2 = b.clone().requires_grad_(True), b.clone().requires_grad_(True)
    ref = b1[rows].max(dim=1).values
    out = _NeighbourMax.apply(b2, rows)
    (ref * w).sum().backward()
    (out * w).sum().backward()
    assert torch.equal(out, ref) and torch.equal(b2.grad, b1.grad)
    assert float(b2.grad[[3, 7]].abs().sum()) > 0 and torch.isclose(b2.grad.sum(), w.sum())  # all of it lands
    assert torch.autograd.gradcheck(_NeighbourMax.apply, (torch.randn(12, 3, dtype=torch.float64, requires_grad=True),
                                                          torch.randint(0, 12, (8, 4))))


def test_crop_region_cache_gives_the_same_crops_and_respects_its_size(labels):
    cfg = CropConfig(num_points=128, neighbour=0.5)
    plain = CropDataset(labels, cfg, augment=True, seed=3)
    cached = CropDataset(labels, cfg, augment=True, seed=3, cache_mb=64)
    small = CropDataset(labels, cfg, augment=True, seed=3, cache_mb=1e-4)  # holds no frame
    for epoch in range(3):
        for i in range(len(plain)):
            a, b, c = plain[(epoch, i)], cached[(epoch, i)], small[(epoch, i)]
            assert all(torch.equal(a[k], b[k]) and torch.equal(a[k], c[k]) for k in a), (epoch, i)
    assert len(cached._cache) == len(plain) and not small._cache
    assert cached._cached == sum(r.nbytes for r in cached._cache.values())
    with LabelFile(labels) as lf:
        frame = lf.frame(0)
        region = crop_region(frame, plain.diameters, cfg)
        # every point of the region is in the frame, in the frame's order, and it is smaller than the frame
        assert len(region.features) < len(frame.features)
        where = {r.tobytes(): i for i, r in enumerate(frame.features)}
        rows = np.array([where[r.tobytes()] for r in region.features])
        assert np.all(np.diff(rows) > 0) and np.array_equal(frame.instance[rows], region.instance)
        # only instances of the listed objects reach into it
        none = crop_region(frame, {}, cfg)
        assert len(none.features) == 0
    assert load_stage2_config(None).cache_mb > 0  # on by default
    with pytest.raises(DetectorError, match="cache_mb"):
        load_stage2_config(None, {"cache_mb": -1})


def test_negative_crops_hold_no_point_of_the_object_they_ask_about(labels):
    """Every negative crop is a ball of the asked object's crop radius in which no frame point is the asked
    object's, asked about one of the network's objects, and reaching no further than the crop region keeps: cut
    from the region, it and the positive crop are the very crops cut from the whole frame (the positive one also
    from the region without negatives, which would cut some negative crops otherwise). Both kinds occur: the
    wrong object at an instance's jittered centre, and any object at a frame point beside it pushed along its ray."""
    from scipy.spatial import cKDTree

    cfg = CropConfig(negatives=0.5)
    kinds = {"wrong object": 0, "beside": 0}
    short = 0  # negative crops that the region without negatives would cut otherwise
    with LabelFile(labels) as lf:
        tab = lf.objects
        dias = {int(i): float(d) for i, d in zip(tab.ids, tab.diameters)}
        for i in range(lf.num_frames):
            f = lf.frame(i)
            region = crop_region(f, dias, cfg)
            narrow = crop_region(f, dias, CropConfig())  # the region without negatives: too small for them
            xyz = f.features[:, :3].astype(np.float64)
            tree = cKDTree(xyz)
            for g in range(len(f.instances)):
                own, true_centre = int(f.instances.obj_id[g]), f.instances.control_points[g][8]
                m = tab.index(own)
                for seed in range(6):
                    c = negative_crop(f, g, dias[own], dias, cfg, np.random.default_rng(seed), NORMALISATION, True)
                    r = negative_crop(region, g, dias[own], dias, cfg, np.random.default_rng(seed), NORMALISATION, True)
                    assert (c is None) == (r is None)
                    pos = [training_crop(fr, g, dias[own], tab.sym_transforms[m], cfg, np.random.default_rng(seed),
                                         NORMALISATION, True) for fr in (f, region, narrow)]
                    assert (pos[0] is None) == (pos[1] is None) == (pos[2] is None)
                    if pos[0] is not None:  # positive crops need only the narrow region
                        assert all(np.array_equal(pos[0][k], q[k]) for q in pos[1:] for k in ("features", "fg", "coords"))
                    if c is None:
                        continue
                    assert np.array_equal(c["features"], r["features"]) and c["obj_id"] == r["obj_id"]
                    n = negative_crop(narrow, g, dias[own], dias, cfg, np.random.default_rng(seed), NORMALISATION, True)
                    short += n is None or not np.array_equal(c["features"], n["features"])
                    oid, centre = c["obj_id"], c["centre"]
                    radius = cfg.radius * dias[oid]
                    assert oid in dias and not c["fg"].any() and len(c["fg"]) == cfg.num_points
                    ball = ball_rows(xyz, centre, radius)
                    asked = np.flatnonzero(f.instances.obj_id == oid)
                    assert len(ball) >= cfg.min_points and not np.isin(f.instance[ball], asked).any()
                    reach = negative_reach(dias[own], max(dias.values()), cfg)
                    assert np.linalg.norm(xyz[ball] - true_centre, axis=1).max() <= reach + 1e-6
                    # a "beside" centre lies 0.3 diameters beyond a frame point on that point's ray
                    p = centre * (1.0 - 0.3 * dias[oid] / np.linalg.norm(centre))
                    if tree.query(p)[0] < 1e-6:
                        kinds["beside"] += 1
                    else:
                        clip = cfg.centre_jitter_clip * dias[own]
                        assert oid != own and np.abs(centre - true_centre).max() <= clip + 1e-9
                        kinds["wrong object"] += 1
    assert min(kinds.values()) >= 5 and short >= 5, (kinds, short)


def test_crop_dataset_with_negatives_adds_background_crops(labels):
    """crop.negatives adds crops without foreground, with only their first symmetry marked; a cache that holds
    every frame gives the items of one that holds none; out-of-range values are a config error."""
    cfg = CropConfig(num_points=128, negatives=1.0)
    plain = CropDataset(labels, cfg, augment=True, seed=2)
    cached = CropDataset(labels, cfg, augment=True, seed=2, cache_mb=64)
    neg = pos = 0
    for epoch in range(2):
        for i in range(len(plain)):
            a, b = plain[(epoch, i)], cached[(epoch, i)]
            assert all(torch.equal(a[k], b[k]) for k in a), (epoch, i)
            empty = (a["fg"].sum(1) == 0)
            neg, pos = neg + int(empty.sum()), pos + int((~empty).sum())
            assert a["sym_mask"][:, 0].all() and not a["sym_mask"][empty, 1:].any()
    assert len(cached._cache) == len(plain)
    assert neg >= 0.3 * pos, (neg, pos)
    for bad in (-0.1, 1.5):
        with pytest.raises(DetectorError, match="negatives"):
            load_stage2_config(None, {"crop.negatives": bad})


def test_crop_dataset_items_and_a_few_steps_lower_the_loss(labels):
    cfg = CropConfig(num_points=128)
    ds = CropDataset(labels, cfg, augment=True, seed=0)
    a, b = ds[(0, 1)], ds[(0, 1)]
    assert all(torch.equal(a[k], b[k]) for k in a)  # deterministic per (epoch, frame)
    assert not torch.equal(ds[(1, 1)]["features"], a["features"])
    batch = collate_crops([ds[(0, i)] for i in range(len(ds))])
    c = len(batch["cls"])
    assert c >= 4 and batch["features"].shape == (c, 128, 9) and batch["coords"].shape[:3] == (c, ds.max_sym, 128)
    assert batch["sym_mask"][:, 0].all()
    torch.manual_seed(0)
    net = CropNet(CropNetConfig(width=32, edge_width=32, global_width=64, head_width=64, k=8), len(ds.class_ids))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        out = net(batch["features"], batch["cls"])
        loss, _ = crop_loss(out, batch["fg"], batch["coords"], batch["sym_mask"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]


# ---------------------------------------------------------------------- the two-stage model end to end (CLI)


def tiny_two_stage_args(s1_steps: int = 2, s2_steps: int = 3) -> list[str]:
    from test_data import TINY_MODEL

    args = ["--quiet", "--set", f"stage1.steps={s1_steps}", "--set", "stage1.num_points=1024",
            "--set", "stage1.batch_size=2", "--set", "stage1.num_workers=0", "--set", "stage1.warmup_steps=1",
            "--set", f"stage2.steps={s2_steps}", "--set", "stage2.num_workers=0", "--set", "stage2.batch_frames=2",
            "--set", "stage2.warmup_steps=1", "--set", "stage2.crop.num_points=64", "--set", "stage2.net.width=16",
            "--set", "stage2.net.edge_width=16", "--set", "stage2.net.global_width=32",
            "--set", "stage2.net.head_width=32", "--set", "stage2.net.k=8"]
    for k, v in TINY_MODEL.items():
        args += ["--set", f"stage1.model.{k}={v}"]
    return args


def test_frames_of_several_label_files_follow_one_another(tmp_path):
    """FrameSource over a list of label files: item i is frame i of the files taken in order (the same arrays as
    the file's own frame), its generator that of item i; files of other objects or another working volume are
    refused in one line."""
    import h5py

    from detector.data.frames import FrameSource
    from test_data import write_synthetic_h5

    a = write_synthetic_h5(tmp_path / "a.h5", num_frames=3, seed=1)
    b = write_synthetic_h5(tmp_path / "b.h5", num_frames=2, seed=2)
    both = FrameSource([a, b], seed=4)
    assert len(both) == 5 and both.class_ids == FrameSource(a).class_ids
    for i, (path, local) in enumerate([(a, 0), (a, 1), (a, 2), (b, 0), (b, 1)]):
        frame, rng, index = both.read((3, i))
        with LabelFile(path) as lf:
            own = lf.frame(local)
        assert index == i and np.array_equal(frame.features, own.features)
        assert np.array_equal(frame.semantic, own.semantic) and np.array_equal(frame.instance, own.instance)
        assert rng.integers(1 << 30) == np.random.default_rng([4, 3, i]).integers(1 << 30)
    with pytest.raises(IndexError):
        both.read(5)
    both.close()
    far = write_synthetic_h5(tmp_path / "far.h5", num_frames=1, seed=3)
    with h5py.File(far, "r+") as f:
        f.attrs["max_depth"] = 3.0
    with pytest.raises(DetectorError, match="different working volumes"):
        FrameSource([a, far])
    other = write_synthetic_h5(tmp_path / "other.h5", num_frames=1, seed=3)
    with h5py.File(other, "r+") as f:
        d = f["objects/diameters"]
        d[0] = 2 * d[0]
    with pytest.raises(DetectorError, match="other objects than"):
        FrameSource([a, other])


def test_stage1_data_trains_stage1_on_its_own_file(labels, tmp_path):
    """--stage1-data: stage 1 learns from its own label file (here a capture without any distractors), stage 2
    from the training file; a file of other objects is refused in one line before anything trains, and the single
    network's presets refuse the option."""
    from detector.cli.app import app as det_app
    from detector.training.checkpoint_file import read_checkpoint
    from test_data import write_synthetic_h5

    run = CliRunner()
    r = run.invoke(argen_app, ["capture-sim", "--frames", "4", "--out", str(tmp_path / "plain"), "--seed", "8",
                               "--set", "clutter.count=[0,0]", "--set", "clutter.on_board=[0,0]", "--quiet"])
    assert r.exit_code == 0, r.output
    plain = tmp_path / "plain.h5"
    run_label(LabelRequest(dataset=tmp_path / "plain", split="train_pbr", out=plain, progress=False,
                           cfg=LabelConfig(max_points=20000)))
    import h5py

    with h5py.File(plain, "r+") as f:  # stage 1's file as one written before part symmetries
        for k in ("part_sym", "part_sym_offsets", "odd_points", "odd_offsets"):
            del f[f"objects/{k}"]
    out = tmp_path / "run"
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--stage1-data", str(plain),
                             *tiny_two_stage_args(2, 2)])
    assert r.exit_code == 0, r.output
    assert read_checkpoint(out / "stage1" / "last.pt")["extra"]["train_file"] == str(plain)
    assert read_checkpoint(out / "model.pt")["extra"]["train_file"] == str(labels)
    # given twice, stage 1 takes both files' frames (4 + 4): one step of batch 4 is half an epoch of them
    r = run.invoke(det_app, ["train", str(labels), "--out", str(tmp_path / "two"), "--stage1-data", str(plain),
                             "--stage1-data", str(labels), *tiny_two_stage_args(1, 1), "--set", "stage1.batch_size=4"])
    assert r.exit_code == 0, r.output
    assert read_checkpoint(tmp_path / "two" / "stage1" / "last.pt")["extra"]["train_file"] == f"{plain} {labels}"
    row = (tmp_path / "two" / "stage1" / "metrics.csv").read_text().splitlines()[1].split(",")
    assert row[:2] == ["1", "0.5"]
    # examples/stage1_beside.sh: stage 1 alone beside the finished stage 2 of a run, with a stage-1 override
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHON": sys.executable, "DETECTOR": str(Path(sys.executable).parent / "detector")}
    beside = tmp_path / "beside"
    call = ["bash", "-c", '. examples/stage1_beside.sh && stage1_beside "$@"', "-", str(out), str(beside), str(labels),
            "{seed: 5}", str(plain)]
    r = subprocess.run(call, cwd=root, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (beside / "stage2" / "last.pt").read_bytes() == (out / "stage2" / "last.pt").read_bytes()
    assert yaml.safe_load((beside / "two_stage.yaml").read_text())["stage1"]["seed"] == 5
    assert yaml.safe_load((beside / "stage1" / "config.yaml").read_text())["seed"] == 5
    assert read_checkpoint(beside / "stage1" / "last.pt")["extra"]["train_file"] == str(plain)
    made = (beside / "model.pt").stat().st_mtime_ns
    assert subprocess.run(call, cwd=root, env=env).returncode == 0 and (beside / "model.pt").stat().st_mtime_ns == made
    # the model poses the mug with the part symmetry stage 2 was taught under, from stage 2's file
    from detector.checkpoint import load_checkpoint
    from detector.infer import checkpoint_objects

    objects = checkpoint_objects(load_checkpoint(out / "model.pt"))[0]
    assert set(objects.part_symmetries) == {2} and len(objects.odd_points[2]) > 1000
    other = write_synthetic_h5(tmp_path / "other.h5", num_frames=2, seed=0)  # objects 1 and 5
    for name, args, why in (
            ("r2", ["--stage1-data", str(other)], "both stages must learn the same objects"),
            ("r3", ["--stage1-data", str(tmp_path / "missing.h5")], "missing.h5"),
            ("r4", ["--stage1-data", str(plain), "--preset", "cpu"], "--stage1-data is for the two-stage model")):
        r = run.invoke(det_app, ["train", str(labels), "--out", str(tmp_path / name), *args, "--quiet"])
        assert r.exit_code == 2 and r.stderr.count("\n") == 1 and why in r.stderr, r.output
        assert not (tmp_path / name / "stage1").exists() and not (tmp_path / name / "last.pt").exists()


def test_two_stage_train_resume_eval_predict(labels, tmp_path):
    """The default `detector train` trains both stages into one model file that eval and predict take, with the
    model's own threshold; --val validates stage 1, --device, --seed and --workers set both stages, the options of
    one network are refused; stage 2 resumes where it stopped, with --set of settings that do not change the
    result; a stage-2 run file alone is refused clearly."""
    import json

    from detector.checkpoint import load_checkpoint
    from detector.cli.app import app as det_app
    from detector.stage1.predictor import network_predictor
    from detector.stage1.sampling import SamplingConfig
    from detector.two_stage import DEFAULTS

    tau = DEFAULTS["geometry"]["tau"]  # the two-stage default, stored in the model file

    run = CliRunner()
    out = tmp_path / "run"
    for flag, value in (("--steps", "3"), ("--batch-size", "2"), ("--lr", "0.01"), ("--epochs", "1"),
                        ("--seg-pretrain-steps", "1")):
        r = run.invoke(det_app, ["train", str(labels), "--out", str(out), flag, value, *tiny_two_stage_args(2, 3)])
        assert r.exit_code == 2 and r.stderr.count("\n") == 1 and f"{flag} applies to one network" in r.stderr
    assert not out.exists()
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), *tiny_two_stage_args(2, 3),
                             "--set", "stage2.keep_every=2", "--set", "stage1.val_every=1", "--val", str(labels),
                             "--device", "cpu", "--seed", "3", "--workers", "0", "--set", "sampling.density=1.5"])
    assert r.exit_code == 0, r.output
    assert all((out / f).is_file() for f in ("model.pt", "stage1/last.pt", "stage2/last.pt"))
    assert (out / "stage1" / "best.pt").is_file()  # --val reached stage 1
    assert all(row["val_loss"] for row in metric_rows(out / "stage1"))
    for stage in ("stage1", "stage2"):
        used = yaml.safe_load((out / stage / "config.yaml").read_text())
        assert (used["device"], used["seed"], used["num_workers"]) == ("cpu", 3, 0), stage
    ck = load_checkpoint(out / "model.pt")
    assert ck.stage2_net is not None and ck.geometry_config["centre_votes"] and ck.geometry_config["tau"] == tau
    assert ck.stage2["class_ids"] == ck.class_ids
    # stage 2 keeps each object's colour level in its training file, and the default inference uses it
    from detector.stage2.colour_level import colour_levels
    assert ck.stage2["colour_levels"] == colour_levels(labels, ck.class_ids)
    assert ck.stage2["infer_config"]["colour_level"] is True
    from detector.checkpoint import add_colour_levels
    from detector.infer import checkpoint_objects, checkpoint_poser
    from detector.training.checkpoint_file import atomic_torch_save, read_checkpoint
    payload = read_checkpoint(out / "model.pt")
    payload["stage2"]["colour_levels"] = None  # a model file written before the levels were kept
    atomic_torch_save(payload, tmp_path / "older.pt")
    older = load_checkpoint(tmp_path / "older.pt")
    with pytest.raises(DetectorError, match="add_colour_levels"):
        checkpoint_poser(older, checkpoint_objects(older)[0])
    assert checkpoint_poser(older, checkpoint_objects(older)[0], sets={"colour_level": False}) is not None
    add_colour_levels(tmp_path / "older.pt", labels)
    assert load_checkpoint(tmp_path / "older.pt").stage2["colour_levels"] == ck.stage2["colour_levels"]
    with pytest.raises(DetectorError, match="not a two-stage model file"):
        add_colour_levels(out / "stage2" / "last.pt", labels)
    with LabelFile(labels) as lf:  # the working volume its points came from, for predict
        assert ck.extra["max_depth"] == pytest.approx(lf.attrs["max_depth"]) and ck.extra["max_depth"] > 0
        frame = lf.frame(0)
    # stage 1 samples at the model file's density (--set at training): more points and keypoints than it trained on,
    # the deeper levels as trained; sampling.density=1 (the default) gives the training's back, and the network
    # predicts at each
    density = SamplingConfig(1.5)
    assert DEFAULTS["sampling"]["density"] == 1
    assert DEFAULTS["sampling"]["fps"] == "tree"  # models trained now find their keypoints with the tree-based FPS
    assert ck.sampling == {"density": 1.5, "passes": DEFAULTS["sampling"]["passes"], "fps": "tree"}
    trained = load_checkpoint(out / "model.pt", sampling={"density": 1})
    assert trained.num_points == 1024 and ck.num_points == density.scaled(1024) > 1024
    assert ck.model_config.npoints[0] == density.scaled(trained.model_config.npoints[0]) > \
        trained.model_config.npoints[0]
    assert ck.model_config.npoints[1:] == trained.model_config.npoints[1:]
    for model in (ck, trained):
        preds = network_predictor(model)(frame)
        assert len(preds.xyz) == model.sampling["passes"] * model.model_config.npoints[0]
        points = {tuple(row) for row in np.asarray(frame.features[:, :3], np.float64)}
        assert all(tuple(row) in points for row in preds.xyz)  # predictions sit on the frame's points
    # a setting that changes the result is refused on resume, for either stage (stage 1 is complete: checked first)
    for key in ("stage1.lr=0.01", "stage2.crop.radius=0.8", "stage1.num_points=512"):
        r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--resume", "--quiet", "--set", key])
        assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "cannot resume with" in r.stderr, (key, r.output)
    # more stage-2 steps and a smaller crop cache: resume continues stage 2 only (stage 1 is complete)
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--resume", "--quiet", "--set", "stage2.steps=5",
                             "--set", "stage2.cache_mb=0.5", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    assert yaml.safe_load((out / "two_stage.yaml").read_text())["stage2"]["cache_mb"] == 0.5
    rows = (out / "stage2" / "metrics.csv").read_text().strip().splitlines()[1:]
    assert [int(x.split(",")[0]) for x in rows] == [1, 2, 3, 4, 5]
    assert load_checkpoint(out / "model.pt").sampling["density"] == 1.5  # the run's own setting, kept
    assert len((out / "stage1" / "metrics.csv").read_text().strip().splitlines()) == 3
    # the kept stage-2 snapshots (keep_every 2, kept across the resume): weights without optimiser state
    from detector.training.checkpoint_file import read_checkpoint

    snaps = sorted(p.name for p in (out / "stage2").glob("step_*.pt"))
    assert snaps == ["step_000002.pt", "step_000004.pt"]
    snap = read_checkpoint(out / "stage2" / "step_000004.pt")["stage2"]
    assert snap["step"] == 4 and snap["train_state"] is None and snap["class_ids"] == ck.stage2["class_ids"]
    # examples/linemod/curve.py evaluates each snapshot (and the final weights) with the run's stage 1
    from conftest import load_repo_script

    curve = load_repo_script("examples/linemod/curve.py")
    points = curve.curve_points(out, labels, 1, stage1_minutes=0.5)
    assert [p["step"] for p in points] == [2, 4, 5]
    minutes = [p["minutes"] for p in points]
    assert 0.5 <= minutes[0] and minutes == sorted(minutes)
    log = out / "stage2" / "metrics.csv"
    assert 0 < curve.train_seconds(log, 2) < curve.train_seconds(log, 4) < curve.train_seconds(log)
    assert all(0.0 <= p[k] <= 100.0 for p in points for k in ("noicp", "icp"))
    # eval and predict with the model's defaults
    rep = tmp_path / "rep"
    r = run.invoke(det_app, ["eval", str(out / "model.pt"), str(labels), "--out", str(rep), "--icp", "--quiet",
                             "--frames", "2"])
    assert r.exit_code == 0, r.output
    s = json.loads((rep / "report.json").read_text())
    assert s["config"]["centre_votes"] and s["config"]["tau"] == tau and "stage2" in s["timing_ms"]
    assert s["sampling"] == {"density": 1.5, "passes": ck.sampling["passes"], "fps": ck.sampling["fps"],
                             "points": ck.num_points, "keypoints": ck.model_config.npoints[0]}
    assert s["config"]["depth_check"] and "depth_check" in s["timing_ms"]
    # --set changes the model's geometry settings for this run; a wrong key or value is a one-line error
    r = run.invoke(det_app, ["eval", str(out / "model.pt"), str(labels), "--out", str(rep), "--icp", "--quiet",
                             "--frames", "2", "--set", "geometry.depth_check=false", "--set", "geometry.tau=0.3"])
    assert r.exit_code == 0, r.output
    s = json.loads((rep / "report.json").read_text())
    assert not s["config"]["depth_check"] and s["config"]["tau"] == 0.3 and "depth_check" not in s["timing_ms"]
    r = run.invoke(det_app, ["eval", str(out / "model.pt"), str(labels), "--out", str(rep), "--icp", "--quiet",
                             "--frames", "2", "--set", "sampling.density=1", "--set", "geometry.tau=0.3",
                             "--set", "sampling.passes=1", "--set", "sampling.fps=trained"])
    assert r.exit_code == 0, r.output
    s = json.loads((rep / "report.json").read_text())
    assert s["config"]["tau"] == 0.3 and s["sampling"] == {"density": 1.0, "passes": 1, "fps": "trained",
                                                             "points": 1024,
                                                             "keypoints": trained.model_config.npoints[0]}
    for bad, word in (("geometry.depth_chek=false", "depth_check"), ("depth_check=false", "geometry.KEY"),
                      ("geometry.other_classes=abc", "number"), ("sampling.densty=2", "sampling.density"),
                      ("sampling.density=20", "[0.25, 8]"), ("sampling.density=abc", "number"),
                      ("sampling.passes=0", "[1, 8]"), ("sampling.passes=1.5", "whole number"),
                      ("sampling.fps=exact", "trained, tree"),
                      ("stage1.lr=0.1", "geometry, sampling and infer"), ("infer.verfy=8", "verify"),
                      ("infer.hypotheses=0", "at least 1")):
        r = run.invoke(det_app, ["eval", str(out / "model.pt"), str(labels), "--out", str(rep), "--set", bad])
        assert r.exit_code == 2 and word in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = run.invoke(det_app, ["eval", str(out / "model.pt"), str(labels), "--out", str(rep), "--quiet", "--frames",
                             "2", "--set", "infer.hypotheses=32", "--set", "infer.verify=4"])
    assert r.exit_code == 0, r.output
    ds = labels.parent / "ds" / "train_pbr" / "000000" / "000001"
    r = run.invoke(det_app, ["predict", str(out / "model.pt"), str(ds), "--out", str(tmp_path / "pred"), "--icp"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "pred" / "poses.png").is_file()
    assert json.loads((tmp_path / "pred" / "poses.json").read_text())["max_depth"] == ck.extra["max_depth"]
    # a stage-2 run's own last.pt is not a model
    r = run.invoke(det_app, ["eval", str(out / "stage2" / "last.pt"), str(labels), "--out", str(rep)])
    assert r.exit_code == 2 and "model.pt" in r.stderr


def test_a_run_folder_with_the_older_names_resumes(labels, tmp_path):
    """A run folder written before the stages had their names (detect/, pose/, two_stage.yaml with a pose section,
    checkpoints with the keys detect / pose / pose_config) resumes in its own folders and gives a model file."""
    from detector.checkpoint import load_checkpoint
    from detector.cli.app import app as det_app
    from detector.training.checkpoint_file import FORMAT, read_checkpoint

    run, out = CliRunner(), tmp_path / "run"
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), *tiny_two_stage_args(2, 2), "--device", "cpu",
                             "--set", "geometry.tau=0.3"])
    assert r.exit_code == 0, r.output
    (out / "stage1").rename(out / "detect")
    (out / "stage2").rename(out / "pose")
    for f in (out / "pose" / "last.pt", out / "model.pt"):  # written back under the old keys (version 2)
        new = torch.load(f, map_location="cpu", weights_only=True)
        old = {"format": FORMAT, "version": 2, "pose": new["stage2"]}
        if "stage1" in new:
            old.update(detect=new["stage1"], extra={"pose_config": new["extra"].pop("geometry_config"),
                                                    **new["extra"]})
        torch.save(old, f)
    cfg = yaml.safe_load((out / "two_stage.yaml").read_text())
    cfg["pose"] = cfg.pop("geometry")
    (out / "two_stage.yaml").write_text(yaml.safe_dump(cfg))
    assert load_checkpoint(out / "model.pt").geometry_config["tau"] == 0.3
    (out / "model.pt").unlink()
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--resume", "--quiet", "--set", "stage2.steps=3"])
    assert r.exit_code == 0, r.output
    assert not (out / "stage1").exists() and not (out / "stage2").exists()
    assert read_checkpoint(out / "pose" / "last.pt")["stage2"]["step"] == 3
    assert len((out / "pose" / "metrics.csv").read_text().strip().splitlines()) == 4
    ck = load_checkpoint(out / "model.pt")
    assert ck.stage2_net is not None and ck.geometry_config["tau"] == 0.3


def test_a_run_started_under_older_defaults_resumes_with_its_own_settings(labels, tmp_path):
    """A run folder whose two_stage.yaml does not name a setting whose default has changed since it started (stage
    1's colour input was `light` before `grey_world`) resumes with the run's own value, for either stage, and its
    two_stage.yaml then names it; a setting named differently from the run's is still refused."""
    from detector.checkpoint import load_checkpoint
    from detector.cli.app import app as det_app
    from detector.training.checkpoint_file import read_checkpoint
    from detector.two_stage import DEFAULTS

    # values other than today's defaults: what the run's file leaves out had other defaults when it started
    colour = "light" if DEFAULTS["stage1"].get("colour", "light") != "light" else "grey_world"
    neighbour = 0.0 if DEFAULTS["stage2"].get("crop.neighbour", 0.0) != 0.0 else 0.5
    run, out = CliRunner(), tmp_path / "run"
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), *tiny_two_stage_args(2, 2), "--device", "cpu",
                             "--set", f"stage1.colour={colour}", "--set", f"stage2.crop.neighbour={neighbour}"])
    assert r.exit_code == 0, r.output
    used = load_checkpoint(out / "model.pt").normalisation.get("colour", "light")
    cfg = yaml.safe_load((out / "two_stage.yaml").read_text())
    del cfg["stage1"]["colour"], cfg["stage2"]["crop.neighbour"]  # as a run's file reads when these were defaults
    (out / "two_stage.yaml").write_text(yaml.safe_dump(cfg))
    (out / "model.pt").unlink()
    # settings added since the run was saved (stage 1's plane_keep and loss.fg_weight, stage 2's crop.negatives)
    # read as the values the run was trained with
    payload = torch.load(out / "stage1" / "last.pt", map_location="cpu", weights_only=False)
    del payload["train_state"]["config"]["plane_keep"], payload["train_state"]["config"]["loss"]["fg_weight"]
    torch.save(payload, out / "stage1" / "last.pt")
    payload = torch.load(out / "stage2" / "last.pt", map_location="cpu", weights_only=False)
    del payload["stage2"]["train_state"]["config"]["crop"]["negatives"]
    torch.save(payload, out / "stage2" / "last.pt")
    today = DEFAULTS["stage1"].get("colour", "light")
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--resume", "--quiet",
                             "--set", f"stage1.colour={today}"])
    assert r.exit_code == 2 and f"cannot resume with colour='{today}'" in r.stderr, r.output
    r = run.invoke(det_app, ["train", str(labels), "--out", str(out), "--resume", "--quiet", "--set", "stage2.steps=3"])
    assert r.exit_code == 0, r.output
    now = yaml.safe_load((out / "two_stage.yaml").read_text())
    assert now["stage1"]["colour"] == colour and now["stage2"]["crop.neighbour"] == neighbour
    part = read_checkpoint(out / "stage2" / "last.pt")["stage2"]
    assert part["step"] == 3 and part["train_state"]["config"]["crop"]["neighbour"] == neighbour
    assert load_checkpoint(out / "model.pt").normalisation.get("colour", "light") == used


TINY_STAGE2 = {"steps": 40, "checkpoint_every": 5, "batch_frames": 2, "num_workers": 0, "warmup_steps": 2,
               "crop.num_points": 64, "net.width": 16, "net.edge_width": 16, "net.global_width": 32,
               "net.head_width": 32, "net.k": 8, "cache_mb": 64.0}

#: Trains the stage-2 run of config file argv[1] on label file argv[2] into folder argv[3] (to be killed).
STAGE2_SCRIPT = """
import sys, torch, yaml
from detector.stage2.train import load_stage2_config, train_stage2
torch.set_num_threads(1)
train_stage2(load_stage2_config(yaml.safe_load(open(sys.argv[1]))), sys.argv[2], sys.argv[3], progress=False)
"""


def metric_rows(run) -> list[dict]:
    """A stage-2 run's metrics.csv without the timing column."""
    import csv

    with open(run / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "steps_per_s"} for r in csv.DictReader(f)]


def test_stage2_killed_and_resumed_with_a_smaller_cache_equals_the_uninterrupted_run(labels, tmp_path):
    """A stage-2 run killed by SIGKILL between two checkpoints and resumed, with its crop cache turned down (what
    a run killed for memory needs), takes the steps of the run that was not interrupted: the same losses, the
    same weights. A setting that changes the result is refused on resume."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from dataclasses import replace

    from detector.config import config_to_dict
    from detector.stage2.train import train_stage2
    from detector.training.checkpoint_file import read_checkpoint

    torch.set_num_threads(1)
    cfg = load_stage2_config(None, TINY_STAGE2)
    train_stage2(cfg, labels, tmp_path / "ref", progress=False)
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(config_to_dict(cfg)))
    for attempt in range(3):
        out = tmp_path / f"run{attempt}"
        proc = subprocess.Popen([sys.executable, "-c", STAGE2_SCRIPT, str(tmp_path / "cfg.yaml"), str(labels),
                                 str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 120
        while not (out / "last.pt").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        assert proc.returncode in (-signal.SIGKILL, 0), err.decode()
        if read_checkpoint(out / "last.pt")["stage2"]["step"] < cfg.steps:
            break  # really interrupted (else it finished first: try again)
    done = read_checkpoint(out / "last.pt")["stage2"]["step"]
    assert done < cfg.steps and done % cfg.checkpoint_every == 0
    with pytest.raises(DetectorError, match="cannot resume with lr"):
        train_stage2(replace(cfg, lr=cfg.lr / 2), labels, out, resume=True, progress=False)
    train_stage2(replace(cfg, cache_mb=0.01, checkpoint_every=7), labels, out, resume=True, progress=False)
    assert metric_rows(out) == metric_rows(tmp_path / "ref")
    assert len(metric_rows(out)) == cfg.steps
    a, b = (read_checkpoint(d / "last.pt")["stage2"]["model_state"] for d in (tmp_path / "ref", out))
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_thread_plan_sets_the_threads_by_step_and_waits_for_stage_1_once(monkeypatch):
    """Stage 2's threads follow its steps, not the clock: the narrow count before ``narrow_steps``, the wide one
    from there, after one wait for stage 1 (made before the threads widen); a stage 2 whose parent is gone stops."""
    import os

    from detector.training.threads import ThreadPlan, default_narrow_steps, split_threads

    assert [split_threads(n) for n in (1, 2, 3, 16)] == [(1, 1), (1, 1), (1, 2), (8, 8)]
    assert default_narrow_steps(3000) == 5100 and default_narrow_steps(0) == 0
    before = torch.get_num_threads()
    waited = []
    try:
        plan = ThreadPlan(3, 1, 2, wait=lambda: waited.append(torch.get_num_threads()))
        seen = []
        for step in range(6):
            plan.before_step(step)
            seen.append(torch.get_num_threads())
        assert seen == [1, 1, 1, 2, 2, 2] and waited == [1]
        resumed = ThreadPlan(3, 1, 2, wait=lambda: waited.append("again"))
        resumed.before_step(4)  # a run resumed past the narrow steps waits too, then widens
        assert torch.get_num_threads() == 2 and waited == [1, "again"]
        with pytest.raises(DetectorError, match="has ended"):
            ThreadPlan(3, 1, 2, parent=os.getpid()).before_step(0)  # this process is not its own parent
    finally:
        torch.set_num_threads(before)


def _threads_column(run) -> list[int]:
    import csv

    with open(run / "stage2" / "metrics.csv", newline="") as f:
        return [int(r["threads"]) for r in csv.DictReader(f)]


def test_stages_side_by_side_give_the_weights_of_one_after_the_other(labels, tmp_path):
    """The two-stage training on a CPU: stage 2 in its own process beside stage 1 gives the weights of the stages
    trained one after the other, bit for bit, both stages; in both runs stage 2's threads widen at the same step,
    and side by side its first steps are taken while stage 1 still trains. An error of stage 2 beside stage 1 ends
    the run with one line and no model file."""
    import os
    from dataclasses import replace

    from detector.cli.app import app as det_app
    from detector.training.checkpoint_file import read_checkpoint
    from detector.two_stage import load_two_stage_config, train_two_stage

    args = tiny_two_stage_args(120, 6)  # stage 1 long enough that stage 2 starts beside it
    sets = dict(a.split("=", 1) for a in args[2::2])
    sets = {k: yaml.safe_load(v) for k, v in sets.items()}
    cfg = load_two_stage_config(None, {**sets, "stage2.narrow_steps": 3, "stage2.keep_every": 1,
                                       "stage1.device": "cpu", "stage2.device": "cpu"})  # side by side: on a CPU
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        for side in (True, False):
            train_two_stage(cfg, labels, tmp_path / str(side), progress=False, side_by_side=side)
            assert torch.get_num_threads() == 2  # given back
    finally:
        torch.set_num_threads(before)
    a, b = (read_checkpoint(tmp_path / name / "model.pt") for name in ("True", "False"))
    for stage in ("stage1", "stage2"):
        wa, wb = a[stage]["model_state"], b[stage]["model_state"]
        assert all(torch.equal(wa[k], wb[k]) for k in wa), stage
    assert _threads_column(tmp_path / "True") == _threads_column(tmp_path / "False") == [1, 1, 1, 2, 2, 2]
    # side by side: stage 2 kept its first step before stage 1 ended, and its wide steps after
    first, wide = (os.path.getmtime(tmp_path / "True" / "stage2" / f"step_00000{k}.pt") for k in (1, 4))
    end1 = os.path.getmtime(tmp_path / "True" / "stage1" / "last.pt")
    assert first < end1 <= wide
    # narrow_steps 0 (runs saved before the setting): one stage after the other, each on all threads
    torch.set_num_threads(2)
    try:
        train_two_stage(replace(cfg, stage2={**cfg.stage2, "narrow_steps": 0}), labels, tmp_path / "old",
                        progress=False)
    finally:
        torch.set_num_threads(before)
    assert _threads_column(tmp_path / "old") == [2] * 6
    assert yaml.safe_load((tmp_path / "True" / "two_stage.yaml").read_text())["stage2"]["narrow_steps"] == 3
    # a run started before the setting (its two_stage.yaml without it) and stopped after stage 1 resumes as it
    # started: stage 2 on all threads; so does one that names it 0
    import shutil

    from detector.config import config_to_dict

    old = tmp_path / "older"
    shutil.copytree(tmp_path / "old" / "stage1", old / "stage1")
    saved = config_to_dict(cfg)
    del saved["stage2"]["narrow_steps"]
    (old / "two_stage.yaml").write_text(yaml.safe_dump(saved))
    torch.set_num_threads(2)
    try:
        train_two_stage(load_two_stage_config(old / "two_stage.yaml"), labels, old, resume=True, progress=False)
    finally:
        torch.set_num_threads(before)
    assert _threads_column(old) == [2] * 6
    assert os.path.getmtime(tmp_path / "old" / "stage1" / "last.pt") <= \
        os.path.getmtime(tmp_path / "old" / "stage2" / "step_000001.pt")
    # a stage 2 that fails beside stage 1 ends stage 1 at its next step, with stage 2's error in one line
    torch.set_num_threads(2)
    try:
        r = CliRunner().invoke(det_app, ["train", str(labels), "--out", str(tmp_path / "bad"),
                                         *tiny_two_stage_args(2000, 3), "--set", "stage2.class_ids=[]",
                                         "--device", "cpu"])
    finally:
        torch.set_num_threads(before)
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "no object classes" in r.stderr, r.output
    assert not (tmp_path / "bad" / "model.pt").exists()
    assert len((tmp_path / "bad" / "stage1" / "metrics.csv").read_text().splitlines()) - 1 < 2000


class TrueCropNet(torch.nn.Module):
    """The crop network's contract filled in from the ground truth: foreground = the points of the instance under
    the crop centre, coordinates = their model coordinates (checks everything of stage 2 but the learning)."""

    def __init__(self, frame, table, class_ids, crop_cfg):
        super().__init__()
        self.frame, self.table, self.class_ids, self.cfg = frame, table, class_ids, crop_cfg

    def forward(self, features, cls):
        from scipy.spatial import cKDTree

        f, inst = self.frame, self.frame.instances
        xyz = f.features[:, :3].astype(np.float64)
        tree = cKDTree(xyz)
        logits, coords = [], []
        for k in range(len(cls)):
            oid = self.class_ids[int(cls[k])]
            m = self.table.index(oid)
            dia = float(self.table.diameters[m])
            rel = features[k, :, :3].double().numpy() * self.cfg.radius * dia  # p - centre, exactly up to float32
            # the centre: the frame point p with p - rel[0] + rel[1] and + rel[2] also frame points
            cand = xyz - rel[0]
            for r in rel[1:3]:
                cand = cand[tree.query(cand + r)[0] < 1e-5]
            c = cand[0]
            j = tree.query(rel + c)[1]
            g = min((g for g in range(len(inst)) if inst.obj_id[g] == oid),
                    key=lambda g: np.linalg.norm(inst.control_points[g][8] - c))
            fg = f.instance[j] == g
            logits.append(torch.from_numpy(np.where(fg, 20.0, -20.0)))
            coords.append(torch.from_numpy(model_coordinates(xyz[j], inst.R[g], inst.t[g], dia).astype(np.float64)))
        return {"fg_logit": torch.stack(logits).float(), "coords": torch.stack(coords).float()}


def centre_detection(objs, oid: int, c: np.ndarray):
    """A stage-1-like detection of object ``oid`` at centre ``c`` (3,) metres: its box moved there, no orientation."""
    from detector.geometry.types import Detection

    shift = c - objs.control_points[oid][8]
    return Detection(oid, 1.0, np.eye(3), shift, 10, objs.control_points[oid] + shift, np.arange(3))


def test_crop_poser_with_true_crop_labels_gives_exact_poses(labels):
    """Stage 2 on true foreground and coordinates, from centres 1.5 cm off: every pose within 2 % of the diameter."""
    from detector.evaluation.metrics import pose_error
    from detector.geometry.types import ObjectInfo
    from detector.stage2.poser import CropPoser

    cfg = CropConfig(num_points=256)
    rng = np.random.default_rng(3)
    with LabelFile(labels) as lf:
        tab = lf.objects
        objs = ObjectInfo.from_table(tab)
        ids = [int(i) for i in tab.ids]
        checked = 0
        for i in range(lf.num_frames):
            f = lf.frame(i)
            inst = f.instances
            poser = CropPoser(TrueCropNet(f, tab, ids, cfg), ids, objs, cfg, NORMALISATION)
            dets = []
            for g in range(len(inst)):
                if inst.num_points[g] < 100 or tab.symmetric[tab.index(int(inst.obj_id[g]))]:
                    continue
                c = inst.control_points[g][8] + rng.normal(0, 0.015 / np.sqrt(3), 3)
                dets.append((g, centre_detection(objs, int(inst.obj_id[g]), c)))
            out = poser([d for _, d in dets], f.features)
            assert len(out) == len(dets)
            for (g, _), d in zip(dets, out):
                m = tab.index(d.obj_id)
                e = pose_error(tab.model_points[m], False, inst.R[g], inst.t[g], d.R, d.t)
                assert e < 0.02 * tab.diameters[m], (i, g, e)
                assert d.points is not None and np.all(f.instance[d.points] == g)
                checked += 1
    assert checked >= 4


def test_pose_from_crop_returns_the_best_fit_first_and_the_other_hypotheses_by_fit():
    """Verification ranks the RANSAC hypotheses by how well the model surface fits the foreground points: with
    60 % right and 40 % wrong coordinates the exact pose comes first, and the alternatives follow by fit."""
    from argen.models.objects import builtin_objects
    from detector.geometry.icp import fit_residuals, fit_rms
    from detector.geometry.types import ObjectInfo
    from detector.stage2.poser import PoserConfig, pose_from_crop

    rng = np.random.default_rng(5)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(1500, seed=3))
    objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.02, -0.01, 0.8])
    m = model[rng.choice(len(model), 200, replace=False)]
    xyz = m @ R.T + t
    mxyz = m.copy()
    wrong = rng.random(200) < 0.4
    mxyz[wrong] = rng.normal(size=(wrong.sum(), 3)) * 0.3 * obj.diameter
    cfg = PoserConfig(verify=8)
    R1, t1, fg, others = pose_from_crop(xyz, np.ones(200), mxyz, obj.diameter, cfg, rng, objs.surface(1))
    assert len(fg) == 200 and len(others) == 7
    assert np.abs(R1 - R).max() < 1e-6 and np.linalg.norm(t1 - t) < 1e-6
    tree, normals = objs.surface(1)
    fits = [fit_rms(fit_residuals(xyz, tree, normals, Ra, ta, 0.05 * obj.diameter), cfg.verify_trim)
            for Ra, ta in [(R1, t1)] + others]
    assert fits == sorted(fits)
    _, _, _, none = pose_from_crop(xyz, np.ones(200), mxyz, obj.diameter, PoserConfig(verify=1), rng, None)
    assert none == []


def busiest_frame(lf):
    """A label file's object table, its :class:`detector.geometry.types.ObjectInfo`, the class ids and the frame with the most
    instances."""
    from detector.geometry.types import ObjectInfo

    tab = lf.objects
    f = max((lf.frame(i) for i in range(lf.num_frames)), key=lambda f: len(f.instances))
    return tab, ObjectInfo.from_table(tab), [int(i) for i in tab.ids], f


def test_each_recentre_cuts_every_crop_again(labels):
    """recentre N cuts each crop N more times around its latest pose's centre. On true labels the second crop's
    pose is already exact, so a third crop gives the same poses."""
    from detector.stage2.poser import CropPoser, PoserConfig

    cfg = CropConfig(num_points=256)
    rng = np.random.default_rng(4)
    with LabelFile(labels) as lf:
        tab, objs, ids, f = busiest_frame(lf)
        inst = f.instances
        dets = []
        for g in range(len(inst)):
            if inst.num_points[g] < 100:
                continue
            c = inst.control_points[g][8] + rng.normal(0, 0.015 / np.sqrt(3), 3)
            dets.append(centre_detection(objs, int(inst.obj_id[g]), c))
        assert len(dets) >= 2
        crops, poses = {}, {}
        for recentre in (1, 2):
            net = TrueCropNet(f, tab, ids, cfg)
            seen = []
            net.register_forward_hook(lambda mod, args, out: seen.append(len(args[1])))
            poser = CropPoser(net, ids, objs, cfg, NORMALISATION, PoserConfig(recentre=recentre))
            out = poser(dets, f.features)
            crops[recentre], poses[recentre] = seen, [(d.R, d.t) for d in out]
    assert crops[1] == [len(dets)] * 2 and crops[2] == [len(dets)] * 3
    for (R0, t0), (R1, t1) in zip(poses[1], poses[2]):
        assert np.abs(t0 - t1).max() < 2e-3 and np.abs(R0 - R1).max() < 0.05


def test_crop_subsets_are_disjoint_while_the_crop_has_enough_points():
    from detector.stage2.crops import sample_crop
    from detector.stage2.poser import crop_subsets

    rows = np.arange(1000, 1700)  # a crop of 700 frame rows
    subs = crop_subsets(rows, 256, 2, np.random.default_rng(0))
    assert [len(s) for s in subs] == [256, 256] and not set(subs[0]) & set(subs[1])
    assert all(np.all(np.diff(s) > 0) and set(s) <= set(rows) for s in subs)
    subs = crop_subsets(rows, 256, 3, np.random.default_rng(0))  # 768 > 700: the third is drawn on its own
    assert [len(s) for s in subs] == [256] * 3 and not set(subs[0]) & set(subs[1]) and set(subs[2]) <= set(rows)
    one = crop_subsets(rows, 256, 1, np.random.default_rng(5))[0]
    assert np.array_equal(one, sample_crop(rows, 256, np.random.default_rng(5)))  # the one-sample design unchanged


def test_pooled_crop_samples_feed_the_pose_all_their_points(labels):
    """With samples 3 the second crop runs the network on three point subsets of each crop and its pose uses the
    foreground points of all three: on true labels every pose is still exact, and each detection carries more
    distinct foreground points than one subset holds."""
    from detector.evaluation.metrics import pose_error
    from detector.stage2.poser import CropPoser, PoserConfig

    cfg = CropConfig(num_points=128)
    rng = np.random.default_rng(6)
    with LabelFile(labels) as lf:
        tab, objs, ids, f = busiest_frame(lf)
        inst = f.instances
        gs = [g for g in range(len(inst)) if inst.num_points[g] >= 250 and not tab.symmetric[tab.index(
            int(inst.obj_id[g]))]]
        assert len(gs) >= 2
        dets = [centre_detection(objs, int(inst.obj_id[g]), inst.control_points[g][8] + rng.normal(0, 0.008, 3))
                for g in gs]
        fg_points = {}
        for samples in (1, 3):
            net = TrueCropNet(f, tab, ids, cfg)
            batches = []
            net.register_forward_hook(lambda mod, args, out: batches.append(len(args[1])))
            out = CropPoser(net, ids, objs, cfg, NORMALISATION, PoserConfig(samples=samples, fit_points=100))(
                dets, f.features)
            assert batches == [len(dets), samples * len(dets)]  # the first crop once, the second `samples` times
            assert len(out) == len(dets)
            for g, d in zip(gs, out):
                m = tab.index(d.obj_id)
                assert pose_error(tab.model_points[m], False, inst.R[g], inst.t[g], d.R, d.t) < 0.02 * tab.diameters[m]
                assert np.all(f.instance[d.points] == g) and len(np.unique(d.points)) == len(d.points)
            fg_points[samples] = [len(d.points) for d in out]
    assert all(b > 1.5 * a for a, b in zip(fg_points[1], fg_points[3])), fg_points


class NoisyCropNet(torch.nn.Module):
    """TrueCropNet's output with seeded noise on the model coordinates (3 % of the diameter, which is what they are
    in) and on the foreground logits: a crop whose pose depends on which points RANSAC draws."""

    def __init__(self, true_net):
        super().__init__()
        self.true_net = true_net

    def forward(self, features, cls):
        out = self.true_net(features, cls)
        g = torch.Generator().manual_seed(len(cls))
        coords = out["coords"] + 0.03 * torch.randn(out["coords"].shape, generator=g, dtype=out["coords"].dtype)
        logit = out["fg_logit"] + torch.randn(out["fg_logit"].shape, generator=g, dtype=out["fg_logit"].dtype)
        return {"fg_logit": logit, "coords": coords}


def test_crops_posed_on_threads_give_the_poses_of_one_thread(labels, monkeypatch):
    """Stage 2 draws each crop's random choices in the crops' order and fits the poses on threads: the same poses,
    bit for bit, as fitting them one after the other, each on its own detection."""
    import detector.stage2.poser as poser_mod
    from detector.stage2.poser import CropPoser, PoserConfig

    cfg = CropConfig(num_points=128)
    rng = np.random.default_rng(12)
    with LabelFile(labels) as lf:
        tab, objs, ids, f = busiest_frame(lf)
        inst = f.instances
        dets = [centre_detection(objs, int(inst.obj_id[g]), inst.control_points[g][8] + rng.normal(0, 0.01, 3))
                for g in range(len(inst)) if inst.num_points[g] >= 150]
        assert len(dets) >= 2
        pcfg = PoserConfig(samples=2, fit_points=100)
        net = NoisyCropNet(TrueCropNet(f, tab, ids, cfg))
        threaded = CropPoser(net, ids, objs, cfg, NORMALISATION, pcfg)(dets, f.features)
        monkeypatch.setattr(poser_mod, "map_threads", lambda fn, items: [fn(x) for x in items])
        alone = CropPoser(net, ids, objs, cfg, NORMALISATION, pcfg)(dets, f.features)
        assert len(threaded) == len(alone) >= 2
        for a, b in zip(threaded, alone):
            assert a.obj_id == b.obj_id
            np.testing.assert_array_equal(a.R, b.R)
            np.testing.assert_array_equal(a.t, b.t)
            np.testing.assert_array_equal(a.points, b.points)


def test_ransac_scored_on_a_subset_refits_on_every_correspondence():
    rng = np.random.default_rng(7)
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.05, 0.0, 0.7])
    m = rng.normal(size=(600, 3)) * 0.05
    p = m @ R.T + t + rng.normal(0, 0.001, m.shape)
    bad = rng.random(600) < 0.4
    p[bad] = t + rng.normal(size=(bad.sum(), 3)) * 0.05
    Re, te, inl = ransac_kabsch(m, p, np.ones(600), 0.01, rng, score_points=64)
    assert np.degrees(np.arccos(np.clip((np.trace(Re.T @ R) - 1) / 2, -1, 1))) < 0.5
    assert np.linalg.norm(te - t) < 0.001
    assert inl.shape == (600,) and inl[~bad].all()  # the inliers of all 600, not only of the 64 scored
    assert inl[bad].mean() < 0.05  # (an outlier may land within 1 cm by chance)


def test_mug_crops_hiding_the_handle_are_taught_up_to_turns_about_its_body(labels):
    """The built-in mug's label-file row has its part symmetry; a crop whose foreground does not show the handle gets
    the 36 turns about the body as targets (after each of its own), each of which keeps its points on the mug's
    surface; one that shows it gets the mug's own."""
    from detector.data.frames import object_table_dict
    from detector.stage2.crops import ODD_SEEN

    cfg = CropConfig(centre_jitter=0.0, colour="none")
    with LabelFile(labels) as lf:
        tab = lf.objects
        m = tab.index(2)
        assert len(tab.part_symmetries[m]) == 35 and len(tab.odd_points[m]) > 1000
        assert all(len(tab.part_symmetries[k]) == 0 for k in range(len(tab)) if k != m)  # bottle, bracket, ...
        from argen.validate import check_objects

        assert check_objects(tab) == []  # argen validate's rules hold for a table with a part symmetry
        objects = object_table_dict(tab)
        sym = crop_symmetries(objects, cfg)
        parts = part_turns(objects, sym)
        own = len(sym[2])  # the identity, and the half turn about x that only the mug's colours break
        assert set(parts) == {2} and len(parts[2].symmetries) == 36 * own
        dia = float(tab.diameters[m])
        surface = cKDTree(np.concatenate([tab.model_points[m], tab.odd_points[m]]))
        seen = set()
        for i in range(lf.num_frames):
            f = lf.frame(i)
            for g in np.flatnonzero(f.instances.obj_id == 2):
                for seed in range(6):
                    c = training_crop(f, g, dia, sym[2], cfg, np.random.default_rng(seed), NORMALISATION,
                                      part=parts[2])
                    if c is None:
                        continue
                    fg = c["fg"] > 0
                    on_odd = np.isfinite(cKDTree(tab.odd_points[m]).query(
                        c["coords"][0][fg] * dia, distance_upper_bound=0.03 * dia)[0]).sum()
                    shown = on_odd >= ODD_SEEN
                    seen.add(bool(shown))
                    assert len(c["coords"]) == (own if shown else 36 * own)
                    np.testing.assert_allclose(c["coords"][0], training_crop(
                        f, g, dia, sym[2], cfg, np.random.default_rng(seed), NORMALISATION)["coords"][0])
                    if not shown:  # every turn keeps the seen body on the mug (scan noise aside)
                        d = surface.query(c["coords"][:, fg].reshape(-1, 3) * dia)[0]
                        assert np.quantile(d, 0.95) < 0.01
    assert True in seen  # the capture shows the handle in some crops


def test_part_turns_count_odd_part_points_and_need_a_part():
    odd = np.array([[0.05, 0.0, z] for z in np.linspace(-0.02, 0.02, 21)])
    part = PartTurns.build(np.eye(4)[None], np.stack([np.eye(4)] * 3), odd, 0.1)
    assert len(part.symmetries) == 4
    handle = odd[:6] / 0.1 + [0.01, 0, 0]  # 1 mm beside the odd part, in diameters
    body = np.array([[0.0, 0.02, 0.0]] * 10) / 0.1
    assert part.shown(handle) and not part.shown(body) and not part.shown(handle[:4])
    assert part.crop_symmetries(np.eye(4)[None], handle).shape == (1, 4, 4)
    assert part.crop_symmetries(np.eye(4)[None], np.vstack([body, handle[:4]])).shape == (4, 4, 4)
    assert PartTurns.build(np.eye(4)[None], np.zeros((0, 4, 4)), odd, 0.1) is None
    assert PartTurns.build(np.eye(4)[None], np.stack([np.eye(4)]), np.zeros((0, 3)), 0.1) is None


def test_colour_levels_are_the_median_of_each_objects_instance_means(labels):
    """An object's level is the median over its instances (with enough labelled points) of their points' mean colour;
    an object the file does not show has none."""
    from detector.stage2.colour_level import colour_levels

    with LabelFile(labels) as lf:
        ids = [int(i) for i in lf.objects.ids]
        means: dict[int, list] = {i: [] for i in ids}
        for k in range(lf.num_frames):
            f = lf.frame(k)
            for g, oid in enumerate(f.instances.obj_id):
                rows = np.flatnonzero(f.instance == g)
                if len(rows) >= 100:
                    means[int(oid)].append(f.features[rows, 3:6].astype(np.float64).mean(0))
    got = colour_levels(labels, [*ids, 999])
    assert got[-1] is None
    for i, level in zip(ids, got):
        assert (level is None) == (not means[i])
        if means[i]:
            assert np.allclose(level, np.median(means[i], axis=0))
            assert all(0 <= v <= 1 for v in level)


def test_level_gain_undoes_an_exposure_within_its_bounds():
    from detector.stage2.colour_level import GAIN_BOUNDS, MIN_POINTS, level_gain, levelled

    rng = np.random.default_rng(0)
    seen = rng.uniform(0.1, 0.6, (200, 3))
    level = [0.3, 0.4, 0.2]
    g = level_gain(seen, level)
    assert np.isclose(g, np.mean(level) / seen.mean())
    for e in (0.7, 0.8, 1.3):  # colours x e: 1 / e times the gain, and the levelled colours are the same
        assert np.isclose(level_gain(seen * e, level), g / e)
        feats = np.concatenate([rng.normal(size=(200, 3)), seen * e, rng.normal(size=(200, 3))], 1)
        assert np.allclose(levelled(feats, level_gain(seen * e, level))[:, 3:6], np.clip(seen * g, 0, 1), atol=1e-6)
        assert np.array_equal(levelled(feats, 1.0), feats.astype(np.float32))
    # a level that far off is not applied (more likely clutter than an exposure)
    assert level_gain(seen * g / (GAIN_BOUNDS[1] * 1.01), level) == 1.0
    assert np.isclose(level_gain(seen * g / (GAIN_BOUNDS[1] * 0.99), level), GAIN_BOUNDS[1] * 0.99)
    assert level_gain(seen * g / (GAIN_BOUNDS[0] * 0.99), level) == 1.0
    assert level_gain(seen[:MIN_POINTS - 1], level) == 1.0 and level_gain(seen, None) == 1.0
    assert level_gain(seen * 0, level) == 1.0


class RecordingTrueCropNet(TrueCropNet):
    """TrueCropNet that keeps the network input of every call (its foreground does not depend on colour)."""

    def __init__(self, *args):
        super().__init__(*args)
        self.inputs = []

    def forward(self, features, cls):
        self.inputs.append(features.clone())
        return super().forward(features, cls)


def test_colour_level_gives_a_darker_cameras_later_crops_the_colours_of_the_brighter_one(labels):
    """With ``colour_level``, the crops after the first are cut from colours brought to the object's training level by
    the gain its first crop's foreground shows: a frame whose colours are all x0.8 (another camera's exposure) feeds
    the network the same later crops as the frame itself, and the same poses come out. Without it they differ."""
    from detector.geometry.types import ObjectInfo
    from detector.stage2.colour_level import colour_levels
    from detector.stage2.poser import CropPoser, PoserConfig

    cfg = CropConfig(num_points=256)
    with LabelFile(labels) as lf:
        tab = lf.objects
        objs = ObjectInfo.from_table(tab)
        ids = [int(i) for i in tab.ids]
        levels = dict(zip(ids, colour_levels(labels, ids)))
        f = lf.frame(0)
        inst = f.instances
        dets = [centre_detection(objs, int(inst.obj_id[g]), inst.control_points[g][8])
                for g in range(len(inst)) if inst.num_points[g] >= 100]
        assert len(dets) >= 2
        darker = np.array(f.features, copy=True)
        darker[:, 3:6] *= 0.8
        seen = {}
        for on in (True, False):
            for name, feats in (("frame", f.features), ("darker", darker)):
                net = RecordingTrueCropNet(f, tab, ids, cfg)
                poser = CropPoser(net, ids, objs, cfg, NORMALISATION, PoserConfig(colour_level=on, samples=2), seed=4,
                                  colour_levels=levels)
                seen[on, name] = (net.inputs, poser(dets, feats))
        for on in (True, False):
            (first, later), out = seen[on, "frame"]
            (first_d, later_d), out_d = seen[on, "darker"]
            assert torch.equal(first[..., :3], first_d[..., :3]) and not torch.allclose(first, first_d)
            assert torch.equal(later[..., :3], later_d[..., :3])
            assert torch.allclose(later, later_d, atol=1e-4) == on
        (_, later), out = seen[True, "frame"]
        (_, later_d), out_d = seen[True, "darker"]
        assert len(out) == len(out_d) == len(dets)
        for a, b in zip(out, out_d):
            assert np.allclose(a.R, b.R) and np.allclose(a.t, b.t) and a.score == b.score
        # a network without colour input, or no levels: the option changes nothing
        for norm, lev in (({**NORMALISATION, "colour": "none"}, levels), (NORMALISATION, None)):
            net = RecordingTrueCropNet(f, tab, ids, cfg)
            CropPoser(net, ids, objs, cfg, norm, PoserConfig(colour_level=True), colour_levels=lev)(dets, darker)
            plain = RecordingTrueCropNet(f, tab, ids, cfg)
            CropPoser(plain, ids, objs, cfg, norm, PoserConfig())(dets, darker)
            assert all(torch.equal(x, y) for x, y in zip(net.inputs, plain.inputs))
