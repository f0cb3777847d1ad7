"""Depth-sensor noise model: Nguyen et al. statistics, quantisation, holes, ranges, normals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from argen.config import NoiseConfig
from argen.sim.noise import (
    _incidence_from_depth,
    apply_noise,
    axial_sigma,
    incidence_angle,
    normals_from_depth,
)

K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
H, W = 480, 640


def small_K(h: int, w: int) -> np.ndarray:
    """K of the LineMOD camera with the principal point moved to the centre of an (h, w) crop."""
    Ks = K.copy()
    Ks[0, 2], Ks[1, 2] = (w - 1) / 2, (h - 1) / 2
    return Ks


def rays(h: int, w: int, Kc: np.ndarray) -> np.ndarray:
    """(h, w, 3) rays K^-1 [u, v, 1]."""
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    return np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(Kc).T


def plane_depth(normal, point, h: int, w: int, Kc: np.ndarray) -> np.ndarray:
    """(h, w) float32 depth of the plane through ``point`` with ``normal`` (camera frame, metres)."""
    n = np.asarray(normal, float)
    return (n @ np.asarray(point, float) / (rays(h, w, Kc) @ n)).astype(np.float32)


def tilted_normal(deg: float, axis: str = "x") -> np.ndarray:
    """Unit normal facing the camera, tilted by ``deg`` from the optical axis about ``axis``."""
    t = np.deg2rad(deg)
    return np.array([0.0, -np.sin(t), -np.cos(t)]) if axis == "x" else np.array([-np.sin(t), 0.0, -np.cos(t)])


# ------------------------------------------------------------------------------------ axial model


def test_axial_sigma_is_nguyen_model():
    cfg = NoiseConfig()
    assert axial_sigma(1.0, 0.0, cfg) == pytest.approx(0.0012 + 0.0019 * 0.36)
    assert axial_sigma(0.4, 0.0, cfg) == pytest.approx(0.0012)
    # angle term 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2 is 0.0001 / 2 at z = 4, theta = pi/4
    assert axial_sigma(4.0, np.pi / 4, cfg) - axial_sigma(4.0, 0.0, cfg) == pytest.approx(0.0001 / 2)
    no_angle = dataclasses.replace(cfg, angle_term=False)
    assert axial_sigma(2.0, 1.2, no_angle) == pytest.approx(axial_sigma(2.0, 0.0, cfg))
    z = np.linspace(0.5, 4.0, 8, dtype=np.float32)[:, None]
    th = np.linspace(0.0, 1.5, 5, dtype=np.float32)[None, :]
    s = axial_sigma(z, th, cfg)
    assert s.shape == (8, 5) and s.dtype == np.float32 and np.all(np.isfinite(s))
    assert np.all(np.diff(s[:, 0]) > 0) and np.all(np.diff(s, axis=1) > 0)


@pytest.mark.parametrize("z", [1.0, 1.5, 2.5])
def test_error_statistics_match_model_including_quantisation(z):
    """On a fronto-parallel plane, Gaussian + quantisation together have Nguyen's total sigma_z."""
    cfg = NoiseConfig()
    depth = np.full((H, W), z, np.float32)
    out = apply_noise(depth, K, cfg, np.random.default_rng(7))
    valid = out > 0
    assert valid.mean() > 0.98  # only random dropout on a clean plane
    err = out[valid].astype(np.float64) - z
    theta = incidence_angle(depth, K, normals_from_depth(depth, K))[valid]
    expected = np.sqrt(np.mean(axial_sigma(np.float64(z), theta.astype(np.float64), cfg) ** 2))
    assert err.std() == pytest.approx(expected, rel=0.05)
    assert err.std() == pytest.approx(axial_sigma(z, 0.0, cfg), rel=0.20)
    assert abs(err.mean()) < 0.05 * expected
    # without the reduction of the Gaussian part the total would be this much larger
    q = z * z * cfg.disparity_step_px / (K[0, 0] * cfg.baseline)
    assert err.std() < 0.97 * np.sqrt(expected**2 + q * q / 12)


def test_quantisation_puts_depth_on_disparity_grid():
    cfg = NoiseConfig(axial_a=0.0, axial_b=0.0, angle_term=False, lateral_px=0.0, edge_dropout=0.0,
                      random_dropout=0.0, grazing_deg=90.0)
    depth = plane_depth(tilted_normal(40.0, "y"), [0, 0, 1.2], H, W, K)
    out = apply_noise(depth, K, cfg, np.random.default_rng(0))
    assert np.all(out > 0)
    fb = K[0, 0] * cfg.baseline
    levels = fb / out.astype(np.float64) / cfg.disparity_step_px
    assert np.abs(levels - np.rint(levels)).max() < 2e-3
    q = depth.astype(np.float64) ** 2 * cfg.disparity_step_px / fb
    assert np.all(np.abs(out - depth) <= 0.5 * q * 1.01 + 1e-6)
    assert np.mean(out != depth) > 0.9
    assert len(np.unique(out)) < 0.5 * len(np.unique(depth))


def test_range_limits_give_zeros():
    cfg = NoiseConfig(random_dropout=0.0, min_range=0.5, max_range=3.0)
    depth = np.full((120, 300), 1.0, np.float32)
    depth[:, :100] = 0.3
    depth[:, 200:] = 4.5
    out = apply_noise(depth, small_K(120, 300), cfg, np.random.default_rng(1))
    assert np.all(out[:, :95] == 0)
    assert np.all(out[:, 205:] == 0)
    assert np.all(out[:, 105:195] > 0)
    assert np.all((out == 0) | ((out >= 0.5) & (out <= 3.0)))


def test_depth_step_makes_holes_along_the_discontinuity_only():
    depth = np.full((160, 200), 0.8, np.float32)
    depth[:, 100:] = 1.2
    depth[60:100, 20:60] = 0.0  # a region without measurement (no jump: nothing to drop around it)
    Kc = small_K(160, 200)
    cols = np.arange(200)[None, :].repeat(160, 0)
    far = np.abs(cols - 99.5) > 4
    far[57:103, 17:63] = False  # lateral jitter may pull the missing block's border in

    def holes(edge_dropout: float) -> np.ndarray:
        cfg = NoiseConfig(random_dropout=0.0, edge_dropout=edge_dropout)
        out = apply_noise(depth, Kc, cfg, np.random.default_rng(2))
        assert np.all(out[63:97, 23:57] == 0)
        return (out == 0) & (depth > 0)

    every = holes(1.0)
    # each row crosses the step at least once: both pixels of that jump are lost
    assert every.sum(axis=1).min() >= 2
    assert not every[far].any()
    some = holes(0.6)
    assert not some[far].any()
    assert 0.45 < some.sum() / every.sum() < 0.75
    assert not holes(0.0)[:, 70:].any()


def test_grazing_plane_returns_nothing():
    cfg = NoiseConfig(edge_dropout=0.0, random_dropout=0.0)
    h, w = 64, 64
    Kc = small_K(h, w)
    steep = plane_depth(tilted_normal(84.0), [0, 0, 1.0], h, w, Kc)  # incidence 84 +- 3.2 deg
    assert np.all(apply_noise(steep, Kc, cfg, np.random.default_rng(3)) == 0)
    kept = apply_noise(steep, Kc, dataclasses.replace(cfg, grazing_deg=90.0), np.random.default_rng(3))
    assert (kept > 0).mean() > 0.9
    mild = plane_depth(tilted_normal(45.0), [0, 0, 1.0], h, w, Kc)
    assert np.all(apply_noise(mild, Kc, cfg, np.random.default_rng(3)) > 0)


def test_lateral_shift_is_nearest_neighbour_with_gaussian_jitter():
    """Only lateral noise on: every output value is some input pixel's, displaced by a rounded N(0, 0.5)."""
    cfg = NoiseConfig(axial_a=0.0, axial_b=0.0, angle_term=False, disparity_step_px=0.0, edge_dropout=0.0,
                      random_dropout=0.0, grazing_deg=90.0, max_range=100.0, lateral_px=0.5)
    h, w = 120, 160
    code = np.arange(h * w).reshape(h, w)
    depth = (1.0 + 1e-3 * code).astype(np.float32)  # encodes each pixel's own index
    out = apply_noise(depth, small_K(h, w), cfg, np.random.default_rng(5))
    src = np.rint((out.astype(np.float64) - 1.0) / 1e-3).astype(int)
    assert np.allclose(out, depth.ravel()[src], atol=0)
    rr, cc = np.divmod(src, w)
    dr = (rr - np.arange(h)[:, None])[3:-3, 3:-3].ravel()
    dc = (cc - np.arange(w)[None, :])[3:-3, 3:-3].ravel()
    p_moved = 0.3173  # P(|N(0, 0.5)| > 0.5)
    for d in (dr, dc):
        assert np.abs(d).max() <= 2
        assert abs(d.mean()) < 0.02
        assert np.mean(d != 0) == pytest.approx(p_moved, abs=0.015)
    assert abs(np.corrcoef(dr, dc)[0, 1]) < 0.03


def test_seed_determinism():
    cfg = NoiseConfig()
    depth = plane_depth(tilted_normal(30.0, "y"), [0, 0, 1.0], H, W, K)
    depth[200:300, 300:400] -= 0.2
    before = depth.copy()
    a = apply_noise(depth, K, cfg, np.random.default_rng(11))
    assert np.array_equal(depth, before)  # input untouched
    b = apply_noise(depth, K, cfg, np.random.default_rng(11))
    c = apply_noise(depth, K, cfg, np.random.default_rng(12))
    assert a.dtype == np.float32 and a.shape == depth.shape
    assert np.array_equal(a, b)
    assert np.mean(a != c) > 0.5


def test_disabled_returns_input_copy():
    depth = plane_depth(tilted_normal(20.0), [0, 0, 1.0], H, W, K)
    depth[:50] = 0.0
    out = apply_noise(depth, K, NoiseConfig(enabled=False), np.random.default_rng(0))
    assert np.array_equal(out, depth) and out.dtype == np.float32
    assert not np.shares_memory(out, depth)


# ------------------------------------------------------------------------------ normals and angles


@pytest.mark.parametrize("deg,axis", [(0.0, "x"), (35.0, "x"), (60.0, "y")])
def test_normals_of_tilted_plane_match_analytic(deg, axis):
    n_true = tilted_normal(deg, axis)
    depth = plane_depth(n_true, [0.05, -0.02, 1.1], H, W, K)
    depth[:40, :40] = 0.0
    normals = normals_from_depth(depth, K)
    assert normals.shape == (H, W, 3) and normals.dtype == np.float32
    valid = depth > 0
    assert np.all(normals[~valid] == 0)
    n = normals[valid]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert (n @ n_true).min() > 1 - 1e-5
    P = depth[..., None] * rays(H, W, K)
    assert np.all(np.einsum("ij,ij->i", n, P[valid]) < 0)  # toward the camera
    theta = incidence_angle(depth, K, normals)
    r = rays(H, W, K)
    expected = np.arccos(-(r @ n_true) / np.linalg.norm(r, axis=-1))
    assert np.abs(theta[valid] - expected[valid]).max() < 1e-3
    assert np.all(theta[~valid] == 0)


def test_normals_next_to_a_step_belong_to_their_own_surface():
    n_left, n_right = tilted_normal(30.0, "y"), tilted_normal(-20.0, "x")
    left = plane_depth(n_left, [0, 0, 0.8], H, W, K)
    right = plane_depth(n_right, [0, 0, 1.3], H, W, K)
    depth = np.where(np.arange(W)[None, :] < 320, left, right)
    normals = normals_from_depth(depth, K)
    assert (normals[:, :320] @ n_left).min() > 1 - 1e-5
    assert (normals[:, 320:] @ n_right).min() > 1 - 1e-5


def test_sphere_normals_and_fast_incidence_path_agree():
    """Curved surface: normals approximate the analytic ones; the internal angle path equals the public one."""
    c, radius = np.array([0.02, -0.01, 0.9]), 0.25
    r = rays(H, W, K)
    rn = r / np.linalg.norm(r, axis=-1, keepdims=True)
    b = rn @ c
    disc = b * b - (c @ c - radius * radius)
    t = np.where(disc > 0, b - np.sqrt(np.maximum(disc, 0)), 0.0)
    depth = (t * rn[..., 2]).astype(np.float32)
    normals = normals_from_depth(depth, K)
    P = depth[..., None] * r
    n_true = (P - c) / radius
    inner = (disc > 0.02 * radius**2) & (normals != 0).any(-1)
    assert inner.sum() > 50_000
    cos = np.einsum("hwc,hwc->hw", normals, n_true)[inner]
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0
    theta = incidence_angle(depth, K, normals)
    assert np.abs(_incidence_from_depth(depth, K) - theta).max() < 1e-3


# ------------------------------------------------------------------------- sensor-profile effects

OFF = dict(lateral_px=0.0, axial_a=0.0, axial_b=0.0, angle_term=False, disparity_step_px=0.0, edge_dropout=0.0,
           random_dropout=0.0, grazing_deg=90.0)


def _step_scene(h=120, w=200, z_fg=0.6, z_bg=1.0, c0=80, c1=120):
    """Background plane at z_bg with a fronto-parallel foreground patch (columns c0..c1) at z_fg."""
    d = np.full((h, w), z_bg, np.float32)
    d[30:90, c0:c1] = z_fg
    return d


def test_shadow_lies_on_the_far_side_of_the_projector_and_has_the_disparity_width():
    from argen.sim.noise import shadow_mask

    Kc = small_K(120, 200)
    d = _step_scene()
    sh = shadow_mask(d, Kc, 0.075)
    width = Kc[0, 0] * 0.075 * (1 / 0.6 - 1 / 1.0)  # 28.6 px: the fg's disparity minus the bg's
    rows = sh[40:80]
    assert not sh[:, 120:].any() and not sh[30:90, 80:120].any()  # nothing right of it or on it
    cols = np.nonzero(rows.any(axis=0))[0]
    assert cols.max() == 79 and abs((cols.max() - cols.min() + 1) - width) <= 1.5
    assert not sh[:25].any()  # rows without the foreground cast no shadow
    out = apply_noise(d, Kc, NoiseConfig(**OFF, shadow=True), np.random.default_rng(0))
    assert np.all(out[sh] == 0) and np.all(out[~sh] > 0)


def test_correlated_field_has_unit_std_and_is_correlated_over_its_window():
    from argen.sim.noise import correlated_field

    f = correlated_field(300, 400, 4.0, np.random.default_rng(1))
    assert f.std() == pytest.approx(1.0, rel=0.05) and abs(f.mean()) < 0.05
    lag = lambda k: np.corrcoef(f[:, :-k].ravel(), f[:, k:].ravel())[0, 1]  # noqa: E731
    assert lag(1) > 0.8 and lag(4) > 0.4 and abs(lag(20)) < 0.05
    # in the model: std correlated_sigma z^2, the same sign over neighbouring pixels
    d = np.full((200, 200), 0.9, np.float32)
    err = apply_noise(d, small_K(200, 200), NoiseConfig(**OFF, correlated_sigma=0.003), np.random.default_rng(2)) - d
    assert err.std() == pytest.approx(0.003 * 0.81, rel=0.15)
    assert np.corrcoef(err[:, :-1].ravel(), err[:, 1:].ravel())[0, 1] > 0.8


def test_per_frame_scale_and_offset_move_the_whole_frame_together():
    d = plane_depth(tilted_normal(20), (0, 0, 1.0), 100, 100, small_K(100, 100))
    cfg = NoiseConfig(**OFF, scale_sigma=0.002, offset_sigma=0.003)
    shifts = []
    for seed in range(40):
        out = apply_noise(d, small_K(100, 100), cfg, np.random.default_rng(seed))
        s, o = np.polyfit(d.ravel(), out.ravel(), 1)  # out = s d + o exactly
        assert np.abs(out - (s * d + o)).max() < 2e-6
        shifts.append((s - 1, o))
    s, o = np.array(shifts).T
    assert 0.001 < s.std() < 0.003 and 0.0018 < o.std() < 0.0045


def test_flying_pixels_take_depths_between_the_two_sides():
    d = _step_scene()
    out = apply_noise(d, small_K(120, 200), NoiseConfig(**OFF, flying=1.0), np.random.default_rng(3))
    moved = np.abs(out - d) > 1e-6
    assert moved.any()
    edge = np.zeros_like(moved)
    edge[29:91, 79:81] = edge[29:91, 119:121] = edge[29:31, 80:120] = edge[89:91, 80:120] = True
    assert not (moved & ~edge).any()  # only next to the discontinuity
    assert np.all((out[moved] > 0.6 - 1e-6) & (out[moved] < 1.0 + 1e-6))
    assert np.ptp(out[moved]) > 0.2  # spread between the sides


def test_stereo_edge_fattening_spreads_the_nearer_side():
    d = _step_scene()
    out = apply_noise(d, small_K(120, 200), NoiseConfig(**OFF, edge_fatten_px=2), np.random.default_rng(4))
    near = np.isclose(out, 0.6)
    assert near[31:89, 78:122].all() and not near[50, 77] and not near[50, 122]  # 2 px wider each side
    assert np.isclose(out[50, 40], 1.0)


def test_multipath_lengthens_concave_corners_only():
    Kc = small_K(120, 160)
    r = rays(120, 160, Kc)
    # a V-shaped valley (concave towards the camera): two planes meeting at the middle column, the corner far
    x = r[..., 0] / r[..., 2]
    d = (0.8 / (1 + 0.5 * np.abs(x))).astype(np.float32)  # nearer at the sides, farthest at the corner
    out = apply_noise(d, Kc, NoiseConfig(**OFF, multipath=0.5), np.random.default_rng(5))
    bias = out - d
    assert bias[:, 78:82].mean() > 5 * max(bias[:, :20].mean(), 1e-5) and bias.min() >= -1e-7
    flat = np.full((120, 160), 0.8, np.float32)
    assert np.abs(apply_noise(flat, Kc, NoiseConfig(**OFF, multipath=0.5), np.random.default_rng(5)) - flat).max() < 1e-6


def test_dark_and_textureless_dropout_need_colour():
    d = np.full((100, 200), 0.9, np.float32)
    rgb = np.full((100, 200, 3), 200, np.uint8)
    rgb[:, :100] = 0  # black left half
    cfg = NoiseConfig(**OFF, dark_dropout=0.6)
    out = apply_noise(d, small_K(100, 200), cfg, np.random.default_rng(6), rgb=rgb)
    assert (out[:, :100] == 0).mean() == pytest.approx(0.6, abs=0.03) and (out[:, 100:] > 0).all()
    assert (apply_noise(d, small_K(100, 200), cfg, np.random.default_rng(6)) > 0).all()  # no colour: no effect
    tex = np.random.default_rng(0).integers(0, 255, (100, 200, 3)).astype(np.uint8)
    tex[:, 100:] = 128  # flat right half
    cfg = NoiseConfig(**OFF, textureless_dropout=0.5)
    out = apply_noise(d, small_K(100, 200), cfg, np.random.default_rng(7), rgb=tex)
    assert (out[:, 110:] == 0).mean() == pytest.approx(0.5, abs=0.04) and (out[:, :90] > 0).all()


# ------------------------------------------------------------------------------------ native pitch


def test_noise_at_the_sensors_own_pitch_when_the_image_is_finer():
    """An image registered to a narrower camera (fx twice the depth camera's) gets the depth camera's noise:
    constant over each 2 x 2 block of image pixels, edge holes twice as wide in image pixels, and the same
    axial statistics as at the native pitch. With native_fx equal to fx nothing changes, draw for draw."""
    from argen.sim.noise import native_pitch

    fine_K = small_K(160, 200)
    fine_K[0, 0] *= 2.0
    fine_K[1, 1] *= 2.0
    depth = np.full((160, 200), 0.8, np.float32)
    depth[:, 100:] = 1.2
    base = NoiseConfig(random_dropout=0.0, edge_dropout=1.0, lateral_px=0.0, native_fx=float(K[0, 0]))
    assert native_pitch(fine_K, base) == pytest.approx(2.0)
    out = apply_noise(depth, fine_K, base, np.random.default_rng(3))
    blocks = out.reshape(80, 2, 100, 2)
    assert np.all(blocks == blocks[:, :1, :, :1])  # one measurement per sensor pixel
    # the edge band: at the native pitch both sensor pixels beside the jump are lost = 4 image pixels a row
    lost = (out == 0).sum(axis=1)
    assert np.all(lost == 4)
    direct = apply_noise(depth, fine_K, dataclasses.replace(base, native_fx=0.0), np.random.default_rng(3))
    assert np.all((direct == 0).sum(axis=1) == 2)  # drawn at the image's pitch: one pixel each side
    # axial noise of the flat part is the model's at 0.8 m either way
    flat = out[:, :90][out[:, :90] > 0]
    assert abs(np.std(flat - 0.8) - float(axial_sigma(np.float32(0.8), np.float32(0.0), base))) < 3e-4
    # native_fx equal to the image's fx: identical draws to the plain model
    same = dataclasses.replace(base, native_fx=float(fine_K[0, 0]))
    a = apply_noise(depth, fine_K, same, np.random.default_rng(4))
    b = apply_noise(depth, fine_K, dataclasses.replace(base, native_fx=0.0), np.random.default_rng(4))
    assert np.array_equal(a, b)
