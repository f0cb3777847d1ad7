"""detector.stage1.ops against brute-force references, and the numpy (loader) path against the torch path."""

import numpy as np
import pytest
import torch

from detector.errors import DetectorError
from detector.stage1.ops import (
    ball_query,
    compute_indices_torch,
    farthest_point_sample,
    EXACT_FPS_MAX_POINTS,
    fps_numpy,
    group,
    precompute_indices,
    three_interpolate,
    three_nn,
)

torch.set_num_threads(1)

SPECS = [(128, 0.15, 16), (48, 0.3, 8), (16, 0.5, 8)]


def cloud(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.5, 0.5, (n, 3)).astype(np.float32)


def naive_fps(p: np.ndarray, n: int) -> np.ndarray:
    """Textbook FPS loop from index 0 (float64)."""
    p = p.astype(np.float64)
    out = [0]
    dist = np.full(len(p), np.inf)
    for _ in range(n - 1):
        dist = np.minimum(dist, ((p - p[out[-1]]) ** 2).sum(1))
        out.append(int(np.argmax(dist)))
    return np.array(out)


def naive_ball(p: np.ndarray, c: np.ndarray, r: float, k: int) -> list[set]:
    """Per centre: the set of indices within r, brute force."""
    d = np.linalg.norm(p[None].astype(np.float64) - c[:, None], axis=-1)
    return [set(np.flatnonzero(row <= r).tolist()) for row in d]


@pytest.mark.parametrize("seed", [0, 1])
def test_fps_matches_naive_loop_both_paths(seed):
    p = cloud(400, seed)
    ref = naive_fps(p, 100)
    assert ref[0] == 0
    np.testing.assert_array_equal(fps_numpy(p, 100), ref)
    got = farthest_point_sample(torch.from_numpy(p)[None].repeat(2, 1, 1), 100)
    np.testing.assert_array_equal(got[0].numpy(), ref)
    np.testing.assert_array_equal(got[1].numpy(), ref)


def fps_gaps(p: np.ndarray, order: np.ndarray) -> np.ndarray:
    """For each step after the first: how much farther (squared, float64) the farthest point was from those chosen
    before it than the point chosen. An exact FPS sequence has all of them 0 (up to float32 rounding)."""
    p = p.astype(np.float64)
    dist = ((p - p[order[0]]) ** 2).sum(1)
    gaps = []
    for i in order[1:]:
        gaps.append(dist.max() - dist[i])
        dist = np.minimum(dist, ((p - p[i]) ** 2).sum(1))
    return np.array(gaps)


def test_fast_fps_on_large_clouds_is_exact_and_deterministic():
    p = cloud(EXACT_FPS_MAX_POINTS + 1000, 7) * np.float32([1.5, 1.0, 0.3]) + np.float32([0, 0, 1.0])
    order = fps_numpy(p, 512)
    assert order.shape == (512,) and order.dtype == np.int64
    assert len(set(order.tolist())) == 512  # distinct points
    assert np.all(fps_gaps(p, order) <= 1e-6)  # each next point is a farthest one from those chosen
    np.testing.assert_array_equal(fps_numpy(p, 512), order)  # a function of the cloud alone
    # as spread as the textbook loop from index 0: the same covering radius
    ref = naive_fps(p, 512)
    cover = [np.sqrt(((p[:, None] - p[s][None]) ** 2).sum(-1)).min(1).max() for s in (order, ref)]
    assert cover[0] == pytest.approx(cover[1], rel=0.1)


def test_clouds_up_to_the_cpu_presets_size_keep_the_loop_from_index_0_and_larger_take_the_tree():
    import fpsample

    from detector.stage1.ops import TREE_FPS_HEIGHT

    p = cloud(EXACT_FPS_MAX_POINTS, 8)
    np.testing.assert_array_equal(fps_numpy(p, 256), naive_fps(p, 256))  # the shipped models' training and numbers
    q = cloud(EXACT_FPS_MAX_POINTS + 1, 8)
    tree = fpsample.bucket_fps_kdline_sampling(q, 256, h=TREE_FPS_HEIGHT, start_idx=0).astype(np.int64)
    np.testing.assert_array_equal(fps_numpy(q, 256), tree)


def test_tree_fps_on_request_is_exact_on_every_cloud_size_and_matches_fpsample_tree():
    """``tree=True`` (inference's ``sampling.fps: tree``) takes the tree-based FPS on clouds of any size, also those
    the training's loop from index 0 samples: still an exact FPS sequence of distinct points, as well spread."""
    import fpsample

    from detector.stage1.ops import TREE_FPS_HEIGHT

    p = cloud(EXACT_FPS_MAX_POINTS, 9) * np.float32([1.2, 0.8, 0.2])
    order = fps_numpy(p, 1024, tree=True)
    assert order.dtype == np.int64 and len(set(order.tolist())) == 1024
    assert np.all(fps_gaps(p, order) <= 1e-6)
    tree = fpsample.bucket_fps_kdline_sampling(p, 1024, h=TREE_FPS_HEIGHT, start_idx=0).astype(np.int64)
    np.testing.assert_array_equal(order, tree)
    loop = fps_numpy(p, 1024)
    np.testing.assert_array_equal(loop, naive_fps(p, 1024))  # without it: the training's loop, unchanged
    assert order[0] != 0  # another first point: not the loop's sequence
    cover = [np.sqrt(((p[:, None] - p[s][None]) ** 2).sum(-1)).min(1).max() for s in (order, loop)]
    assert cover[0] == pytest.approx(cover[1], rel=0.1)
    for n, m in ((64, 32), (2 ** TREE_FPS_HEIGHT, 8), (2 ** TREE_FPS_HEIGHT - 1, 8), (5, 5)):  # the small deep levels
        q = cloud(n, n)
        got = fps_numpy(q, m, tree=True)
        assert len(set(got.tolist())) == m and np.all(fps_gaps(q, got) <= 1e-6)
        if n < 2 ** TREE_FPS_HEIGHT:  # under the tree's least size: the loop from index 0
            np.testing.assert_array_equal(got, naive_fps(q, m))
        else:  # from the tree's least size on: the tree
            tree_q = fpsample.bucket_fps_kdline_sampling(q, m, h=TREE_FPS_HEIGHT, start_idx=0).astype(np.int64)
            np.testing.assert_array_equal(got, tree_q)
    idx = precompute_indices(p, [(1024, 0.1, 8), (256, 0.2, 8)], tree_fps=True)
    np.testing.assert_array_equal(idx["sample_0"], order)
    np.testing.assert_array_equal(idx["sample_1"], fps_numpy(p[order], 256, tree=True))


def test_ball_query_membership_and_order():
    p = cloud(300, 2)
    centres_idx = naive_fps(p, 40)
    c = p[centres_idx]
    r, k = 0.2, 12
    ref = naive_ball(p, c, r, k)
    pt = torch.from_numpy(p)[None]
    for idx in (precompute_indices(p, [(40, r, k)])["group_0"], ball_query(pt, pt[:, centres_idx], r, k)[0].numpy()):
        assert idx.shape == (40, k)
        for i in range(40):
            members = set(idx[i].tolist())
            assert members <= ref[i]  # only points inside the ball
            assert len(members) == min(k, len(ref[i]))  # as many distinct points as fit
            assert idx[i, 0] == centres_idx[i]  # nearest first: the centre itself
            d = np.linalg.norm(p[idx[i]] - c[i], axis=1)
            assert np.all(np.diff(d[: len(members)]) >= -1e-7)  # sorted by distance
            assert np.all(idx[i, len(members):] == idx[i, 0])  # padding repeats the nearest
            if len(ref[i]) > k:  # the k nearest of the ball
                assert d[: len(members)].max() <= np.sort(np.linalg.norm(p[list(ref[i])] - c[i], axis=1))[k - 1] + 1e-7


def test_three_nn_weights_and_interpolation():
    known, unknown = cloud(50, 3), cloud(80, 4)
    d = np.linalg.norm(unknown[:, None].astype(np.float64) - known[None], axis=-1)
    ref_idx = np.argsort(d, axis=1)[:, :3]
    ref_d = np.take_along_axis(d, ref_idx, 1)
    ref_w = (1 / ref_d) / (1 / ref_d).sum(1, keepdims=True)
    idx, w = three_nn(torch.from_numpy(unknown)[None], torch.from_numpy(known)[None])
    np.testing.assert_array_equal(idx[0].numpy(), ref_idx)
    np.testing.assert_allclose(w[0].numpy(), ref_w, rtol=1e-4)
    # interpolating the coordinates themselves with weights summing to 1 stays inside the neighbours' hull
    feats = torch.from_numpy(known)[None].double()
    interp = three_interpolate(feats, idx, w)[0].numpy()
    np.testing.assert_allclose(interp, (known[ref_idx] * ref_w[..., None]).sum(1), atol=1e-5)
    # a known point interpolates to its own value
    self_idx, self_w = three_nn(torch.from_numpy(known)[None], torch.from_numpy(known)[None])
    np.testing.assert_allclose(three_interpolate(feats, self_idx, self_w)[0].numpy(), known, atol=1e-6)


@pytest.mark.parametrize("offset", [0.0, 1.2])  # also a cloud in front of the camera (float32 cancellation)
def test_numpy_and_torch_paths_agree(offset):
    p = cloud(600, 5) + np.float32([0.1, -0.2, offset])
    a = precompute_indices(p, SPECS)
    b = compute_indices_torch(torch.from_numpy(p)[None], SPECS)
    assert set(a) == set(b) == {"sample_0", "sample_1", "sample_2", "group_0", "group_1", "group_2",
                                "interp_1_idx", "interp_1_w", "interp_2_idx", "interp_2_w"}
    for key in a:
        assert a[key].shape == tuple(b[key].shape[1:]), key
        if key.endswith("_w"):
            assert a[key].dtype == np.float32 and b[key].dtype == torch.float32
            np.testing.assert_allclose(a[key], b[key][0].numpy(), atol=1e-4)
        else:
            assert a[key].dtype == np.int64 and b[key].dtype == torch.int64
            np.testing.assert_array_equal(a[key], b[key][0].numpy(), err_msg=key)
    # level structure: interp_1 maps the 128 level-1 points onto the 48 level-2 points
    assert a["interp_1_idx"].shape == (128, 3) and a["interp_1_idx"].max() < 48
    assert a["group_1"].max() < 128 and a["group_2"].max() < 48


def test_group_gathers_rows_per_batch():
    vals = torch.arange(2 * 5 * 2, dtype=torch.float32).view(2, 5, 2)
    idx = torch.tensor([[[4, 0]], [[1, 1]]])
    out = group(vals, idx)
    assert out.shape == (2, 1, 2, 2)
    assert torch.equal(out[0, 0], vals[0, [4, 0]]) and torch.equal(out[1, 0], vals[1, [1, 1]])


def test_small_levels_pad_and_bad_specs_raise():
    p = cloud(10, 6)
    out = precompute_indices(p, [(4, 10.0, 32), (2, 10.0, 8)])
    assert out["group_0"].shape == (4, 32) and set(out["group_0"][0].tolist()) == set(range(10))
    assert out["group_1"].shape == (2, 8)
    t = compute_indices_torch(torch.from_numpy(p)[None], [(4, 10.0, 32), (2, 10.0, 8)])
    np.testing.assert_array_equal(t["sample_1"][0].numpy(), out["sample_1"])
    with pytest.raises(DetectorError, match="cannot take 20 points"):
        precompute_indices(p, [(20, 0.1, 8)])
    with pytest.raises(DetectorError, match="shape"):
        precompute_indices(p[:, :2], [(4, 0.1, 8)])
