"""Stage 1's thinned support plane (detector.data.plane, detector.stage1.dataset.frame_rows): the plane found is the
table's, never an object's beyond the plane distance; thinning keeps every off-plane point; a setting of 1 draws
exactly as before; a model trained with it samples the same way at inference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_data import write_synthetic_h5
from test_train import tiny_config

from detector.checkpoint import load_checkpoint
from detector.data.plane import PLANE_DISTANCE, dominant_plane, thin_plane_rows
from detector.stage1.dataset import PointDataset, frame_rows, inference_batch, sample_rows
from detector.stage1.train import train

torch.set_num_threads(1)


def tabletop(seed: int = 0, table: int = 20000, per_box: int = 3000):
    """A tilted table (0.8 m square, 2 mm depth noise) about 1 m from the camera with two 0.1 m boxes standing on
    it. Returns xyz (N,3) metres, height (N,) metres above the table, is_table (N,) bool."""
    rng = np.random.default_rng(seed)
    a = np.deg2rad(35)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])  # table frame -> camera
    t = np.array([0.0, 0.0, 1.0])
    pts = [np.c_[rng.uniform(-0.4, 0.4, (table, 2)), rng.normal(0, 0.002, table)]]
    for cx in (-0.15, 0.12):  # the boxes' surfaces: four sides and the top
        u = rng.uniform(-0.05, 0.05, (per_box, 2))
        h = rng.uniform(0, 0.1, per_box)
        side = rng.integers(0, 5, per_box)
        p = np.where(side[:, None] == 0, np.c_[u[:, 0], u[:, 1], np.full(per_box, 0.1)],
                     np.where(side[:, None] == 1, np.c_[np.full(per_box, 0.05), u[:, 1], h],
                              np.where(side[:, None] == 2, np.c_[np.full(per_box, -0.05), u[:, 1], h],
                                       np.where(side[:, None] == 3, np.c_[u[:, 0], np.full(per_box, 0.05), h],
                                                np.c_[u[:, 0], np.full(per_box, -0.05), h]))))
        pts.append(p + [cx, 0.05, 0.0])
    local = np.concatenate(pts)
    return local @ R.T + t, local[:, 2], np.arange(len(local)) < table


def test_the_dominant_plane_is_the_table_and_no_object_above_it():
    xyz, height, is_table = tabletop()
    on = dominant_plane(xyz, np.random.default_rng(0))
    assert on[is_table].mean() > 0.99  # 2 mm noise: every table point within the 1 cm
    # box points only where they touch the table (the fitted plane is the true one within the noise)
    assert np.all(height[on & ~is_table] <= 1.5 * PLANE_DISTANCE) and (on & ~is_table).sum() < 0.1 * (~is_table).sum()
    assert np.array_equal(on, dominant_plane(xyz, np.random.default_rng(0)))  # seeded: the same plane every time


def test_no_plane_is_dropped_where_no_plane_holds_a_fifth_of_the_frame():
    rng = np.random.default_rng(1)
    ball = rng.normal(size=(5000, 3))
    ball = 0.2 * ball / np.linalg.norm(ball, axis=1, keepdims=True) + [0, 0, 1]
    assert not dominant_plane(ball, rng).any()
    assert not dominant_plane(ball[:2], rng).any()


@pytest.mark.parametrize("keep", [0.0, 0.1, 0.5])
def test_thinning_keeps_every_point_off_the_plane_and_a_share_of_it(keep):
    xyz, height, is_table = tabletop()
    rows = thin_plane_rows(xyz, 1024, keep, np.random.default_rng(2))
    assert np.all(np.diff(rows) > 0)
    on = dominant_plane(xyz, np.random.default_rng(2))  # the same draws: the same plane
    assert set(np.flatnonzero(~on)) <= set(rows.tolist())
    assert np.count_nonzero(on[rows]) == round(keep * on.sum())
    # a frame with few points off the plane is filled up from the plane to the points stage 1 takes
    many = thin_plane_rows(xyz, 9000, keep, np.random.default_rng(2))
    assert len(many) == max(9000, (~on).sum() + round(keep * on.sum()))
    assert np.array_equal(thin_plane_rows(xyz, 1024, 1.0, np.random.default_rng(2)), np.arange(len(xyz)))


def test_frame_rows_without_thinning_draws_as_before_and_with_it_sees_more_of_the_objects():
    xyz, height, is_table = tabletop()
    feats = np.c_[xyz, np.zeros((len(xyz), 6))]
    assert np.array_equal(frame_rows(feats, 4096, np.random.default_rng(3)),
                          sample_rows(len(xyz), 4096, np.random.default_rng(3)))
    all_rows = frame_rows(feats, 4096, np.random.default_rng(3))
    thin = frame_rows(feats, 4096, np.random.default_rng(3), plane_keep=0.1)
    assert len(np.unique(thin)) == 4096
    assert np.count_nonzero(~is_table[thin]) > 2.5 * np.count_nonzero(~is_table[all_rows])


@pytest.fixture(scope="module")
def h5_path(tmp_path_factory):
    return write_synthetic_h5(tmp_path_factory.mktemp("data") / "syn.h5", num_frames=4, seed=0)


def test_a_model_trained_with_thinning_samples_the_same_way_at_inference(h5_path, tmp_path):
    train(tiny_config(steps=1, plane_keep=0.2), h5_path, tmp_path / "r", progress=False)
    ck = load_checkpoint(tmp_path / "r" / "last.pt")
    assert ck.plane_keep == 0.2
    ds = PointDataset(h5_path, ck.model_config, 1024, plane_keep=0.2)
    frame = ds.read(1)[0]
    table = np.asarray(frame.semantic) == 0
    batch = inference_batch(frame.features, ck.model_config, 1024, seed=0, plane_keep=ck.plane_keep)
    plain = inference_batch(frame.features, ck.model_config, 1024, seed=0)
    rows, plain_rows = batch["point_index"].numpy(), plain["point_index"].numpy()
    assert table[rows].mean() < table[plain_rows].mean() - 0.1
    # training items are rows of the frame with their own labels, as without thinning
    item = ds[1]
    assert item["cls"].shape == (1024,) and int((item["cls"] > 0).sum()) > int((~table[plain_rows]).sum())


def test_a_run_saved_before_the_setting_existed_resumes_as_it_was_trained(h5_path, tmp_path):
    """Runs saved before ``plane_keep`` have no such setting: they resume (and a two-stage run folder with them
    resumes) as runs of every point, and refuse another value."""
    from detector.errors import DetectorError

    train(tiny_config(steps=1), h5_path, tmp_path / "r", progress=False)
    last = tmp_path / "r" / "last.pt"
    payload = torch.load(last, map_location="cpu", weights_only=False)
    del payload["train_state"]["config"]["plane_keep"]  # as written before the setting existed
    torch.save(payload, last)
    train(tiny_config(steps=2), h5_path, tmp_path / "r", progress=False, resume=True)
    assert load_checkpoint(last).step == 2 and load_checkpoint(last).plane_keep == 1.0
    payload = torch.load(last, map_location="cpu", weights_only=False)
    del payload["train_state"]["config"]["plane_keep"]
    torch.save(payload, last)
    with pytest.raises(DetectorError, match="plane_keep"):
        train(tiny_config(steps=3, plane_keep=0.5), h5_path, tmp_path / "r", progress=False, resume=True)
