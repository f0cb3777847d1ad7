"""Tests of detector.data and detector.stage1.dataset: items agree with the label file, augmentation keeps labels
consistent, bad files fail clearly.

Also home of ``write_synthetic_h5``: a small exact label file (boxes resting on a table, ray cast from a
pinhole camera) written with h5py following docs/hdf5-schema.md; test_train.py imports it.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import h5py
import numpy as np
import pytest

# ----------------------------------------------------------------------------------------------------------
# Synthetic label files
# ----------------------------------------------------------------------------------------------------------

#: (id, name, box min, box max, colour) of the synthetic objects; ids are not contiguous on purpose.
SYN_OBJECTS = [
    (1, "crate", (-0.04, -0.025, 0.0), (0.04, 0.025, 0.06), (0.85, 0.2, 0.15)),
    (5, "tower", (-0.025, -0.025, 0.0), (0.025, 0.025, 0.10), (0.15, 0.35, 0.85)),
]


def box_corners(bmin, bmax) -> np.ndarray:
    """The 8 corners of an axis-aligned box in the schema's order, then its centre: (9, 3) float64."""
    xs, ys, zs = zip(bmin, bmax)
    corners = np.array(list(itertools.product(xs, ys, zs)), dtype=np.float64)
    return np.concatenate([corners, corners.mean(axis=0, keepdims=True)])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_cam (4, 4) of an OpenCV camera at ``eye`` looking at ``target``, world z up."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def _ray_box(d_cam: np.ndarray, R: np.ndarray, t: np.ndarray, bmin, bmax):
    """Depth scale s (ray point s*d) and camera-frame normal of the first hit of rays d with a posed box."""
    o = -R.T @ t
    d = d_cam @ R  # R.T @ d for each ray
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (np.asarray(bmin) - o) / d
        t2 = (np.asarray(bmax) - o) / d
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    tmin = np.where(np.isnan(tmin), -np.inf, tmin)
    tmax = np.where(np.isnan(tmax), np.inf, tmax)
    near, far = tmin.max(axis=1), tmax.min(axis=1)
    hit = (near <= far) & (near > 0)
    axis = tmin.argmax(axis=1)
    n_m = np.zeros_like(d)
    n_m[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    return np.where(hit, near, np.inf), n_m @ R.T


def synthetic_frame(rng: np.random.Generator, width: int = 64, height: int = 48):
    """One exact frame: dict of points/* rows and instance rows (camera frame, metres)."""
    K = np.array([[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1.0]])
    az, el, dist = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 1.1), rng.uniform(0.35, 0.45)
    eye = dist * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    T_cw = np.linalg.inv(_look_at(eye, np.array([0.0, 0.0, 0.03])))
    # instances: 2-3 boxes at separated places on the table, random yaw
    n_inst = int(rng.integers(2, 4))
    pos: list[np.ndarray] = []
    while len(pos) < n_inst:
        p = rng.uniform(-0.11, 0.11, 2)
        if all(np.linalg.norm(p - q) > 0.11 for q in pos):
            pos.append(p)
    kinds = rng.integers(0, len(SYN_OBJECTS), n_inst)
    kinds[:2] = [0, 1]  # both classes in every frame
    Rs, ts = [], []
    for p in pos:
        T_wo = np.eye(4)
        T_wo[:3, :3] = _rot_z(rng.uniform(0, 2 * np.pi))
        T_wo[:2, 3] = p
        T_co = T_cw @ T_wo
        Rs.append(T_co[:3, :3])
        ts.append(T_co[:3, 3])
    # rays through pixel centres; a ray point at depth z is z * d
    v, u = np.mgrid[0:height, 0:width]
    pix = np.stack([v.ravel(), u.ravel()], axis=1).astype(np.int32)
    d = np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(u.size)], axis=1) @ np.linalg.inv(K).T
    # table: world plane z = 0, |x|, |y| < 0.3
    n_c, p0 = T_cw[:3, 2], T_cw[:3, 3]
    with np.errstate(divide="ignore"):
        s_tab = (n_c @ p0) / (d @ n_c)
    hit_w = (s_tab[:, None] * d - p0) @ T_cw[:3, :3]
    s_tab = np.where((s_tab > 0) & (np.abs(hit_w[:, :2]).max(axis=1) < 0.3), s_tab, np.inf)
    depths, normals = [s_tab], [np.broadcast_to(n_c, d.shape)]
    for R, t, k in zip(Rs, ts, kinds):
        s, n = _ray_box(d, R, t, SYN_OBJECTS[k][2], SYN_OBJECTS[k][3])
        depths.append(s)
        normals.append(n)
    depths = np.stack(depths)
    which = depths.argmin(axis=0)
    s = depths[which, np.arange(d.shape[0])]
    keep = np.isfinite(s)
    which, s, d, pix = which[keep], s[keep], d[keep], pix[keep]
    xyz = s[:, None] * d
    nrm = np.stack(normals)[which, np.flatnonzero(keep)]
    nrm = np.where((np.sum(nrm * xyz, axis=1) > 0)[:, None], -nrm, nrm)
    inst = which - 1
    kinds_pt = np.where(inst >= 0, kinds[np.maximum(inst, 0)], -1)
    base = np.array([o[4] for o in SYN_OBJECTS] + [(0.55, 0.5, 0.45)])[kinds_pt]
    rgb = np.clip(base * (0.6 + 0.4 * np.abs(nrm[:, 2:3])) + rng.normal(0, 0.02, base.shape), 0, 1)
    ids = np.array([o[0] for o in SYN_OBJECTS])
    semantic = np.where(inst >= 0, ids[np.maximum(kinds_pt, 0)], 0)
    cps = np.stack([box_corners(SYN_OBJECTS[k][2], SYN_OBJECTS[k][3]) @ R.T + t for R, t, k in zip(Rs, ts, kinds)])
    return {
        "features": np.concatenate([xyz, rgb, nrm], axis=1).astype(np.float32),
        "pixel": pix,
        "semantic": semantic.astype(np.int32),
        "instance": inst.astype(np.int32),
        "cam_K": K.astype(np.float32),
        "obj_id": ids[kinds].astype(np.int32),
        "R": np.stack(Rs).astype(np.float32),
        "t": np.stack(ts).astype(np.float32),
        "control_points": cps.astype(np.float32),
        "num_points": np.bincount(inst[inst >= 0], minlength=n_inst).astype(np.int32),
    }


def write_synthetic_h5(path: Path, num_frames: int = 4, seed: int = 0, width: int = 64, height: int = 48) -> Path:
    """Write a schema-v1 label file of ``num_frames`` exact synthetic frames (two box objects, ids 1 and 5)."""
    from argen.h5 import FrameLabels, InstanceTable, ObjectTable, point_control_points, write_label_file

    rng = np.random.default_rng(seed)
    cps = np.stack([box_corners(o[2], o[3]) for o in SYN_OBJECTS]).astype(np.float32)
    objects = ObjectTable(
        ids=np.array([o[0] for o in SYN_OBJECTS], np.int32), names=[o[1] for o in SYN_OBJECTS],
        diameters=np.array([np.linalg.norm(np.subtract(o[3], o[2])) for o in SYN_OBJECTS], np.float32),
        symmetric=np.zeros(len(SYN_OBJECTS), bool), corners=cps[:, :8], control_points=cps,
        model_points=cps[:, [0, 3, 5, 6, 8]], sym_transforms=[np.eye(4, dtype=np.float32)[None]] * len(SYN_OBJECTS))

    def labels(f: dict, i: int) -> FrameLabels:
        n_inst = len(f["obj_id"])
        inst = InstanceTable(obj_id=f["obj_id"], gt_index=np.arange(n_inst, dtype=np.int32), R=f["R"], t=f["t"],
                             control_points=f["control_points"], visib_fract=np.ones(n_inst, np.float32),
                             num_points=f["num_points"])
        return FrameLabels(scene_id=0, im_id=i, cam_K=f["cam_K"], image_size=np.array([height, width], np.int32),
                           features=f["features"], pixel=f["pixel"], semantic=f["semantic"], instance=f["instance"],
                           control_points=point_control_points(f["control_points"], f["instance"]), instances=inst)

    attrs = dict(created_by="tests.synthetic", source_dataset="synthetic", source_split="train",
                 source_argen_json="", max_points=width * height, max_depth=2.0, subsampling="voxel+random")
    frames = (labels(synthetic_frame(rng, width, height), i) for i in range(num_frames))
    return write_label_file(path, attrs, objects, frames, compression=None)


# ----------------------------------------------------------------------------------------------------------
# Tests
# ----------------------------------------------------------------------------------------------------------

import pickle  # noqa: E402

import torch  # noqa: E402
from pykdtree.kdtree import KDTree  # noqa: E402

from detector.data.augment import NORMALISATION, augment, input_normalisation, normalise_features  # noqa: E402
from detector.data.batches import collate
from detector.errors import DetectorError  # noqa: E402
from detector.stage1.dataset import PointDataset, class_index, inference_batch, sample_rows
from detector.stage1.train import make_config  # noqa: E402

torch.set_num_threads(1)
NUM_POINTS = 1024


def small_model_config():
    """The cpu preset made tiny (TINY_MODEL) for fast tests."""
    from detector.stage1.network import ModelConfig, preset

    return ModelConfig.from_dict({**preset("cpu").to_dict(), **TINY_MODEL})


#: Overrides that make the cpu preset tiny (fewer keypoints and channels) for fast tests.
TINY_MODEL: dict = {
    "npoints": [256, 64, 32, 16, 8], "nsamples": [16, 8, 8, 8, 8],
    "sa_mlps": [[8, 16], [16, 32], [32, 32], [32, 64], [64, 64]],
    "fp_mlps": [[64], [64], [32], [32]], "head_channels": 32,
}


@pytest.fixture(scope="module")
def h5_path(tmp_path_factory) -> Path:
    return write_synthetic_h5(tmp_path_factory.mktemp("data") / "syn.h5", num_frames=4, seed=0)


@pytest.fixture(scope="module")
def frames(h5_path):
    """The file's frames read back with plain h5py: list of (features, semantic, instance, control points)."""
    out = []
    with h5py.File(h5_path, "r") as f:
        po, io = f["frames/point_offsets"][:], f["frames/instance_offsets"][:]
        for i in range(len(po) - 1):
            inst = f["points/instance"][po[i]:po[i + 1]]
            cps = f["instances/control_points"][io[i]:io[i + 1]][np.maximum(inst, 0)]
            cps[inst < 0] = 0
            out.append((f["points/features"][po[i]:po[i + 1]], f["points/semantic"][po[i]:po[i + 1]], inst, cps))
    return out


def test_sample_rows_distinct_when_enough_and_all_rows_when_too_few():
    rng = np.random.default_rng(0)
    rows = sample_rows(1000, 300, rng)
    assert len(np.unique(rows)) == 300 and rows.min() >= 0 and rows.max() < 1000
    assert np.array_equal(rows, sample_rows(1000, 300, np.random.default_rng(0)))
    few = sample_rows(50, 120, rng)
    assert len(few) == 120 and set(few.tolist()) == set(range(50))
    with pytest.raises(DetectorError):
        sample_rows(0, 10, rng)


def test_class_index_ranks_known_ids_and_sends_others_to_background():
    sem = np.array([0, 1, 5, 3, 5, 7, 1])
    assert class_index(sem, [1, 5]).tolist() == [0, 1, 2, 0, 2, 0, 1]
    assert class_index(sem, [5]).tolist() == [0, 0, 1, 0, 1, 0, 0]


def test_items_are_rows_of_the_file_with_their_labels(h5_path, frames):
    ds = PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=False, seed=3)
    assert len(ds) == 4 and ds.class_ids == [1, 5]
    for i in (0, 2):
        item = ds[i]
        feats, sem, inst, cps = frames[i]
        d, rows = KDTree(feats[:, :3].astype(np.float64)).query(item["features"][:, :3].numpy().astype(np.float64))
        assert d.max() < 1e-7 and len(np.unique(rows)) == NUM_POINTS  # distinct rows of frame i
        rgb = item["features"][:, 3:6].numpy() * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]
        np.testing.assert_allclose(rgb, feats[rows, 3:6], atol=1e-6)
        np.testing.assert_array_equal(item["features"][:, 6:].numpy(), feats[rows, 6:])
        assert item["cls"].tolist() == class_index(sem[rows], [1, 5]).tolist()
        assert item["instance"].tolist() == inst[rows].tolist()
        np.testing.assert_array_equal(item["control_points"].numpy(), cps[rows])
        assert int(item["frame"]) == i
        assert item["sample_0"].dtype == torch.int64


def test_items_are_deterministic_per_seed_epoch_and_frame(h5_path):
    cfg = small_model_config()
    a = PointDataset(h5_path, cfg, NUM_POINTS, augment=True, seed=1)
    b = pickle.loads(pickle.dumps(PointDataset(h5_path, cfg, NUM_POINTS, augment=True, seed=1)))
    x, y = a[(2, 1)], b[(2, 1)]
    assert x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
    assert not torch.equal(a[(3, 1)]["features"], x["features"])  # another epoch, another draw
    c = PointDataset(h5_path, cfg, NUM_POINTS, augment=True, seed=2)
    assert not torch.equal(c[(2, 1)]["features"], x["features"])


def test_padding_repeats_points_of_small_frames(h5_path, frames):
    n = len(frames[0][0])
    ds = PointDataset(h5_path, small_model_config(), n + 500, augment=False, seed=0)
    xyz = ds[0]["features"][:, :3].numpy()
    assert len(np.unique(xyz, axis=0)) == len(np.unique(frames[0][0][:, :3], axis=0))


def test_augmentation_moves_points_and_labels_together(frames):
    feats, sem, inst, cps = frames[1]
    rng = np.random.default_rng(5)
    f2, c2 = augment(feats, cps, rng)
    obj = inst >= 0
    # the roll about the optical axis keeps z and the distance to the axis of every control point
    np.testing.assert_allclose(c2[..., 2], cps[..., 2], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(c2[..., :2], axis=-1), np.linalg.norm(cps[..., :2], axis=-1), atol=1e-6)
    assert np.abs(c2[obj] - cps[obj]).max() > 1e-3  # it did rotate
    assert np.all(c2[~obj] == 0)
    # point-to-control-point geometry is kept up to the xyz jitter (<= 5 mm per axis)
    rel0 = np.linalg.norm(cps[obj] - feats[obj, None, :3], axis=-1)
    rel1 = np.linalg.norm(c2[obj] - f2[obj, None, :3], axis=-1)
    assert np.abs(rel1 - rel0).max() <= 0.005 * np.sqrt(3) + 1e-6
    # normals turn with the points: unit length, same angle to the centre direction up to jitter
    np.testing.assert_allclose(np.linalg.norm(f2[:, 6:9], axis=1), 1.0, atol=1e-5)
    dot0 = np.sum(feats[obj, 6:9] * (cps[obj, 8] - feats[obj, :3]), axis=1)
    dot1 = np.sum(f2[obj, 6:9] * (c2[obj, 8] - f2[obj, :3]), axis=1)
    assert np.abs(dot1 - dot0).max() <= 0.005 * np.sqrt(3) + 1e-6
    assert f2[:, 3:6].min() >= 0 and f2[:, 3:6].max() <= 1 and not np.allclose(f2[:, 3:6], feats[:, 3:6])


def test_camera_colour_augmentation_changes_a_whole_frame_like_another_camera(frames):
    feats, sem, inst, cps = frames[1]
    ratios, grey, none = [], 0, 0
    for seed in range(60):
        f_light, c_light = augment(feats, cps, np.random.default_rng(seed))
        f_cam, c_cam = augment(feats, cps, np.random.default_rng(seed), colour="camera")
        # the geometry is the light augmentation's: only the colours differ
        np.testing.assert_array_equal(f_cam[:, [0, 1, 2, 6, 7, 8]], f_light[:, [0, 1, 2, 6, 7, 8]])
        np.testing.assert_array_equal(c_cam, c_light)
        rgb = f_cam[:, 3:6]
        assert rgb.min() >= 0 and rgb.max() <= 1
        if not rgb.any():
            none += 1
        elif np.allclose(rgb, rgb.mean(1, keepdims=True), atol=0.1):
            grey += 1
        else:
            ratios.append(rgb.mean() / feats[:, 3:6].mean())
    assert 0 < none < 10 and 0 < grey < 15  # some depth-only and grey frames, most in colour
    assert min(ratios) < 0.75 and max(ratios) > 1.25  # spans exposures x0.7 and x1.3 (light stays within 15 %)
    modes = "light, camera, camera_tone, camera_rgb, rank, grey_world, grey_world_rgb or none"
    with pytest.raises(DetectorError, match=f"colour must be {modes}"):
        make_config("cpu", {"colour": "sepia"})


def test_camera_rgb_is_camera_without_its_grey_and_colourless_frames(frames):
    """colour "camera_rgb": under the same seed the frame is "camera"'s bit for bit where that one kept its colours;
    where "camera" made it grey or colourless, "camera_rgb" keeps three distinct channels (its draws otherwise the
    same: same geometry and labels). Over 60 seeds some frames differ and none is grey."""
    feats, sem, inst, cps = frames[1]
    differ = 0
    for seed in range(60):
        f_cam, c_cam = augment(feats, cps, np.random.default_rng(seed), colour="camera")
        f_rgb, c_rgb = augment(feats, cps, np.random.default_rng(seed), colour="camera_rgb")
        np.testing.assert_array_equal(f_rgb[:, [0, 1, 2, 6, 7, 8]], f_cam[:, [0, 1, 2, 6, 7, 8]])
        np.testing.assert_array_equal(c_rgb, c_cam)
        rgb, cam = f_rgb[:, 3:6], f_cam[:, 3:6]
        assert rgb.min() >= 0 and rgb.max() <= 1
        assert np.abs(rgb - rgb.mean(1, keepdims=True)).max() > 0.1  # never grey, never zeros
        if not np.array_equal(rgb, cam):
            differ += 1
            assert not cam.any() or np.allclose(cam, cam.mean(1, keepdims=True), atol=0.1)  # camera's grey or none
    assert 0 < differ < 20


def test_grey_world_rgb_is_camera_rgb_balanced_as_grey_world(h5_path, frames):
    """colour "grey_world_rgb": the colour changes are "camera_rgb"'s bit for bit (never grey or colourless), and the
    network input is balanced as "grey_world"'s: its checkpoint normalisation is that mode's, so inference needs no
    new case; a dataset item is the grey-world balance of "camera_rgb"'s item."""
    from detector.data.augment import grey_world

    feats, sem, inst, cps = frames[1]
    for seed in range(20):
        a = augment(feats, cps, np.random.default_rng(seed), colour="camera_rgb")
        b = augment(feats, cps, np.random.default_rng(seed), colour="grey_world_rgb")
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    assert input_normalisation("grey_world_rgb") == input_normalisation("grey_world") != NORMALISATION
    rgb_item, gw_item = (PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=True, seed=4, colour=c)[(1, 2)]
                         for c in ("camera_rgb", "grey_world_rgb"))
    assert torch.equal(rgb_item["features"][:, [0, 1, 2, 6, 7, 8]], gw_item["features"][:, [0, 1, 2, 6, 7, 8]])
    rgb = rgb_item["features"][:, 3:6].numpy() * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]
    balanced = gw_item["features"][:, 3:6].numpy() * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]
    np.testing.assert_allclose(balanced, grey_world(rgb), atol=1e-5)


def items_of_two_colour_modes(h5_path, base: str, mode: str):
    """Item (epoch 1, frame 2) of two augmented datasets alike but for their colour modes, after checking that their
    geometry and labels are the same and that ``mode``'s checkpoint normalisation names it; and ``base``'s colours
    as the label file stores them ((N,3) in [0, 1], from its normalised input)."""
    a, b = (PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=True, seed=4, colour=c)[(1, 2)]
            for c in (base, mode))
    assert input_normalisation(mode) == {**NORMALISATION, "colour": mode}
    for k in ("cls", "instance", "control_points"):
        assert torch.equal(a[k], b[k])
    assert torch.equal(a["features"][:, [0, 1, 2, 6, 7, 8]], b["features"][:, [0, 1, 2, 6, 7, 8]])
    return a, b, a["features"][:, 3:6].numpy() * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]


def test_rank_frames_are_the_same_under_another_cameras_colours(h5_path, frames):
    """colour "rank" in stage 1: an item's colour channels are the ranks of the frame's sampled colours after
    "camera_tone"'s change (same geometry and labels under the same seed); the inference input of a frame is the
    same when another camera's exposure, white balance and gamma changed its colours, and differs without ranks."""
    from detector.data.augment import colour_ranks
    from detector.stage1.dataset import inference_batch

    a, b, rgb = items_of_two_colour_modes(h5_path, "camera_tone", "rank")
    np.testing.assert_allclose(b["features"][:, 3:6].numpy(), colour_ranks(rgb), atol=1e-5)
    feats = frames[0][0]
    other = feats.copy()
    other[:, 3:6] = (feats[:, 3:6] * np.array([0.75, 0.7, 0.6], np.float32)) ** np.float32(1.3)
    cfg = small_model_config()

    def inputs(norm):
        return [inference_batch(f, cfg, NUM_POINTS, seed=1, normalisation=norm)["features"] for f in (feats, other)]

    x, y = inputs(input_normalisation("rank"))
    assert torch.equal(x, y)
    x, y = inputs(NORMALISATION)
    assert not torch.allclose(x[..., 3:6], y[..., 3:6])


def test_grey_world_frames_are_the_same_under_another_cameras_gains(h5_path, frames):
    """colour "grey_world" in stage 1: an item's colour channels are the grey-world balance of "camera"'s changed
    colours (same geometry and labels under the same seed: balanced, each channel's mean is 0.5); a frame's inference
    input is the same under another camera's exposure and white balance (gains per channel), and differs under
    another gamma or without the balance."""
    from detector.data.augment import grey_world
    from detector.stage1.dataset import inference_batch

    a, b, rgb = items_of_two_colour_modes(h5_path, "camera", "grey_world")
    balanced = b["features"][:, 3:6].numpy() * NORMALISATION["rgb_std"] + NORMALISATION["rgb_mean"]
    np.testing.assert_allclose(balanced, grey_world(rgb), atol=1e-5)
    np.testing.assert_allclose(balanced.mean(0)[rgb.mean(0) > 0.01], 0.5, atol=0.02)  # up to the clip at 2
    feats = frames[0][0]
    cfg = small_model_config()

    def inputs(norm, change):
        other = feats.copy()
        other[:, 3:6] = change(feats[:, 3:6])
        return [inference_batch(f, cfg, NUM_POINTS, seed=1, normalisation=norm)["features"] for f in (feats, other)]

    x, y = inputs(input_normalisation("grey_world"), lambda c: c * np.array([0.75, 0.6, 0.9], np.float32))
    torch.testing.assert_close(x, y, atol=1e-5, rtol=0)
    x, y = inputs(input_normalisation("grey_world"), lambda c: c ** np.float32(1.5))
    assert not torch.allclose(x[..., 3:6], y[..., 3:6], atol=1e-3)
    x, y = inputs(NORMALISATION, lambda c: c * np.array([0.75, 0.6, 0.9], np.float32))
    assert not torch.allclose(x[..., 3:6], y[..., 3:6], atol=1e-3)


def test_colour_none_gives_the_network_geometry_only(h5_path, frames):
    """colour "none": the items' colour channels are zero whatever the frame's colours, the geometry and labels are
    those of the colour input, and the normalisation a checkpoint keeps says so."""
    light = PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=True, seed=4)
    none = PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=True, seed=4, colour="none")
    assert none.normalisation == {**NORMALISATION, "colour": "none"} and "colour" not in light.normalisation
    for key in (0, (1, 2)):
        a, b = light[key], none[key]
        assert not a["features"][:, 3:6].eq(0).all() and b["features"][:, 3:6].eq(0).all()
        for k in ("cls", "instance", "control_points"):
            assert torch.equal(a[k], b[k])
        assert torch.allclose(a["features"][:, [0, 1, 2, 6, 7, 8]], b["features"][:, [0, 1, 2, 6, 7, 8]], atol=1e-6)
    feats = frames[0][0]
    assert np.array_equal(normalise_features(feats, none.normalisation)[:, 3:6], np.zeros((len(feats), 3)))
    assert np.array_equal(normalise_features(feats, none.normalisation)[:, [0, 1, 2, 6, 7, 8]],
                          feats[:, [0, 1, 2, 6, 7, 8]])


def test_collate_stacks_items(h5_path):
    ds = PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=False, seed=0)
    items = [ds[1], ds[3]]
    batch = collate(items)
    assert set(batch) == set(items[0])
    for k in batch:
        assert batch[k].shape == (2, *items[0][k].shape)
        assert torch.equal(batch[k][1], items[1][k])
    assert batch["frame"].tolist() == [1, 3]


def test_loader_workers_open_the_file_themselves_and_give_the_same_items(h5_path):
    ds = PointDataset(h5_path, small_model_config(), NUM_POINTS, augment=True, seed=0)
    ds[0]  # an open handle in this process must not travel to the worker
    keys = [[(1, 3), (1, 0)]]
    loader = torch.utils.data.DataLoader(ds, batch_sampler=keys, collate_fn=collate, num_workers=1)
    (batch,) = list(loader)
    expect = collate([ds[k] for k in keys[0]])
    assert all(torch.equal(batch[k], expect[k]) for k in expect)
    ds.close()


def test_inference_batch_points_index_the_input_rows(frames):
    feats = frames[0][0]
    batch = inference_batch(feats, small_model_config(), NUM_POINTS, seed=4)
    rows = batch["point_index"].numpy()
    assert batch["features"].shape == (1, NUM_POINTS, 9) and len(np.unique(rows)) == NUM_POINTS
    np.testing.assert_array_equal(batch["features"][0, :, :3].numpy(), feats[rows, :3])
    assert batch["sample_0"].shape[0] == 1
    with pytest.raises(DetectorError, match=r"\(N, 9\)"):
        inference_batch(feats[:, :6], small_model_config(), NUM_POINTS)


def _rewrite(src: Path, dst: Path, name: str, data) -> Path:
    """Copy of label file ``src`` with dataset ``name`` replaced by ``data``."""
    import shutil

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        del f[name]
        f[name] = data
    return dst


@pytest.mark.parametrize("name, make", [
    ("points/features", lambda a: a[:, :6]),                      # wrong shape
    ("points/features", lambda a: a.astype(np.int32)),           # wrong dtype
    ("points/semantic", lambda a: a.astype(np.float32) + 0.5),   # wrong dtype
])
def test_malformed_file_is_a_clear_error(h5_path, tmp_path, name, make):
    with h5py.File(h5_path, "r") as f:
        data = make(f[name][:])
    bad = _rewrite(h5_path, tmp_path / "bad.h5", name, data)
    with pytest.raises(DetectorError) as exc:
        PointDataset(bad, small_model_config(), NUM_POINTS)
    msg = str(exc.value)
    assert "\n" not in msg and str(bad) in msg and name.split("/")[1] in msg


def test_missing_or_foreign_file_is_a_clear_error(tmp_path):
    with pytest.raises(DetectorError, match="nope.h5"):
        PointDataset(tmp_path / "nope.h5", small_model_config(), NUM_POINTS)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(DetectorError):
        PointDataset(other, small_model_config(), NUM_POINTS)
