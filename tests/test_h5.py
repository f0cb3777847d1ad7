"""argen.h5: label file round trip, streaming writer atomicity, clear errors on bad files."""

from __future__ import annotations

import pickle

import h5py
import numpy as np
import pytest

from argen.errors import ArgenError
from argen.h5 import (
    FrameLabels,
    InstanceTable,
    LabelFile,
    LabelWriter,
    ObjectTable,
    point_control_points,
    write_label_file,
)
from argen.models.objects import box_corners

ATTRS = dict(created_by="test", source_dataset="synthetic", source_split="train", source_argen_json="",
             max_points=500, max_depth=2.0, subsampling="voxel+random")


def object_table() -> ObjectTable:
    lo = np.array([[-0.03, -0.02, -0.01], [-0.05, -0.05, -0.05]])
    size = np.array([[0.06, 0.04, 0.02], [0.1, 0.1, 0.1]])
    corners = np.stack([box_corners(a, b) for a, b in zip(lo, size)]).astype(np.float32)
    cps = np.concatenate([corners, corners.mean(1, keepdims=True)], 1)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0]).astype(np.float32)
    return ObjectTable(ids=np.array([2, 7], np.int32), names=["a", "bee"], diameters=np.array([0.075, 0.17], np.float32),
                       symmetric=np.array([False, True]), corners=corners, control_points=cps,
                       model_points=np.random.default_rng(0).normal(size=(2, 16, 3)).astype(np.float32) * 0.02,
                       sym_transforms=[np.eye(4, dtype=np.float32)[None], np.stack([np.eye(4, dtype=np.float32), flip])])


def random_frame(rng: np.random.Generator, objects: ObjectTable, im_id: int) -> FrameLabels:
    n, m = int(rng.integers(0, 300)), int(rng.integers(0, 4))
    obj_id = rng.choice(objects.ids, m).astype(np.int32)
    R = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0].astype(np.float32)
    t = rng.uniform(-0.2, 0.2, (m, 3)).astype(np.float32) + [0, 0, 0.8]
    cps = np.stack([objects.control_points[objects.index(o)] @ r.T + tt for o, r, tt in zip(obj_id, R, t)]) \
        if m else np.zeros((0, 9, 3))
    instance = rng.integers(-1, m, n).astype(np.int32)
    semantic = np.where(instance >= 0, obj_id[np.maximum(instance, 0)] if m else 0, 0).astype(np.int32)
    inst = InstanceTable(obj_id=obj_id, gt_index=np.arange(m, dtype=np.int32), R=R, t=t.astype(np.float32),
                         control_points=cps.astype(np.float32), visib_fract=rng.uniform(0, 1, m).astype(np.float32),
                         num_points=np.bincount(instance[instance >= 0], minlength=m).astype(np.int32))
    K = np.array([[500, 0, 320], [0, 500, 240], [0, 0, 1]], np.float32)
    return FrameLabels(scene_id=1, im_id=im_id, cam_K=K, image_size=np.array([480, 640], np.int32),
                       features=rng.normal(size=(n, 9)).astype(np.float32),
                       pixel=rng.integers(0, 480, (n, 2)).astype(np.int32), semantic=semantic, instance=instance,
                       control_points=point_control_points(inst.control_points, instance), instances=inst)


def assert_frames_equal(a: FrameLabels, b: FrameLabels) -> None:
    assert (a.scene_id, a.im_id) == (b.scene_id, b.im_id)
    for k in ("cam_K", "image_size", "features", "pixel", "semantic", "instance", "control_points"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    for k in ("obj_id", "gt_index", "R", "t", "control_points", "visib_fract", "num_points"):
        np.testing.assert_array_equal(getattr(a.instances, k), getattr(b.instances, k), err_msg=k)


@pytest.fixture()
def written(tmp_path):
    rng = np.random.default_rng(3)
    objs = object_table()
    frames = [random_frame(rng, objs, i) for i in range(7)]
    path = write_label_file(tmp_path / "x.h5", ATTRS, objs, frames)
    return path, objs, frames


def test_round_trip_frames_objects_and_attrs(written):
    path, objs, frames = written
    with LabelFile(path) as lf:
        assert lf.num_frames == len(frames) == lf.attrs["num_frames"]
        assert lf.attrs["schema_version"] == 1 and lf.attrs["source_split"] == "train"
        for i, fr in enumerate(frames):
            assert_frames_equal(lf.frame(i), fr)
        o = lf.objects
        assert o.names == ["a", "bee"] and o.index(7) == 1
        np.testing.assert_array_equal(o.control_points, objs.control_points)
        np.testing.assert_array_equal(o.model_points, objs.model_points)
        assert [len(s) for s in o.sym_transforms] == [1, 2]
        np.testing.assert_array_equal(o.sym_transforms[1][0], np.eye(4))
        with pytest.raises(ArgenError, match="object id 3"):
            o.index(3)
        with pytest.raises(IndexError):
            lf.frame(len(frames))


def test_plain_h5py_reads_the_documented_layout(written):
    path, objs, frames = written
    with h5py.File(path, "r") as f:
        off = f["frames/point_offsets"][()]
        ioff = f["frames/instance_offsets"][()]
        i = 4
        feats = f["points/features"][off[i]:off[i + 1]]
        np.testing.assert_array_equal(feats, frames[i].features)
        inst = f["points/instance"][off[i]:off[i + 1]]
        cps = f["instances/control_points"][ioff[i]:ioff[i + 1]]
        fg = inst >= 0
        np.testing.assert_array_equal(cps[inst[fg]], frames[i].control_points[fg])
        assert f["points/features"].compression == "lzf"


def test_point_control_points_zero_for_background():
    cps = np.arange(2 * 27, dtype=np.float32).reshape(2, 9, 3)
    out = point_control_points(cps, np.array([-1, 1, 0, -1]))
    assert np.all(out[[0, 3]] == 0)
    np.testing.assert_array_equal(out[1], cps[1])
    np.testing.assert_array_equal(out[2], cps[0])


def test_writer_leaves_nothing_on_error(tmp_path):
    objs = object_table()
    rng = np.random.default_rng(1)
    with pytest.raises(RuntimeError):
        with LabelWriter(tmp_path / "y.h5", ATTRS, objs) as w:
            w.append(random_frame(rng, objs, 0))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_clear_errors_for_missing_truncated_foreign_and_wrong_version(written, tmp_path):
    path = written[0]
    with pytest.raises(ArgenError, match="not found"):
        LabelFile(tmp_path / "none.h5")
    cut = tmp_path / "cut.h5"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(ArgenError, match="cut.h5") as e:
        LabelFile(cut).frame(0)
    assert "\n" not in str(e.value)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(ArgenError, match="not an HDF5"):
        LabelFile(text)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(ArgenError, match="not an argen label file"):
        LabelFile(foreign)
    v2 = tmp_path / "v2.h5"
    v2.write_bytes(path.read_bytes())
    with h5py.File(v2, "r+") as f:
        f.attrs["schema_version"] = 2
    with pytest.raises(ArgenError, match="schema version 2"):
        LabelFile(v2)
    with h5py.File(v2, "r+") as f:
        f.attrs["schema_version"] = 1
        del f["instances/R"]
    with pytest.raises(ArgenError, match="instances/R"):
        LabelFile(v2)


def test_label_file_refuses_pickling(written):
    with LabelFile(written[0]) as lf:
        with pytest.raises(TypeError, match="each worker"):
            pickle.dumps(lf)


def test_extend_appends_whole_files_like_frame_by_frame(written, tmp_path):
    path, objs, frames = written
    part2 = write_label_file(tmp_path / "p2.h5", ATTRS, objs, frames[:2], compression=None)
    with LabelWriter(tmp_path / "joined.h5", ATTRS, objs, compression="gzip") as w:
        for p in (part2, path):
            with LabelFile(p) as lf:
                w.extend(lf)
    with LabelFile(tmp_path / "joined.h5") as lf:
        assert lf.num_frames == 2 + len(frames)
        for i, fr in enumerate(frames[:2] + frames):
            assert_frames_equal(lf.frame(i), fr)


def test_corrupt_chunk_is_a_one_line_error(written, tmp_path):
    path = written[0]
    with h5py.File(path, "r") as f:
        offset = f["points/features"].id.get_chunk_info(0).byte_offset
    bad = tmp_path / "bad.h5"
    data = bytearray(path.read_bytes())
    data[offset:offset + 64] = bytes(64)
    bad.write_bytes(bytes(data))
    with LabelFile(bad) as lf:
        with pytest.raises(ArgenError, match="damaged: cannot read frame 0") as e:
            lf.frame(0)
    assert "\n" not in str(e.value)


def test_part_symmetries_and_odd_points_round_trip_and_old_files_have_none(tmp_path):
    objs = object_table()
    path = write_label_file(tmp_path / "old.h5", ATTRS, objs, [])
    with LabelFile(path) as lf:
        assert lf.objects.part_symmetries == [] and lf.objects.odd_points == []
    turn = np.eye(4, dtype=np.float32)
    turn[:2, :2] = [[0, -1], [1, 0]]
    objs.part_symmetries = [np.zeros((0, 4, 4), np.float32), turn[None]]
    objs.odd_points = [np.zeros((0, 3), np.float32), np.arange(12, dtype=np.float32).reshape(4, 3) / 100]
    path = write_label_file(tmp_path / "new.h5", ATTRS, objs, [])
    with LabelFile(path) as lf:
        for a, b in zip(lf.objects.part_symmetries + lf.objects.odd_points, objs.part_symmetries + objs.odd_points):
            np.testing.assert_array_equal(a, b)
    with h5py.File(path, "r+") as f:  # offsets that do not match the data: a one-line error
        f["objects/odd_offsets"][2] = 3
    with pytest.raises(ArgenError, match="odd_points"):
        LabelFile(path)
