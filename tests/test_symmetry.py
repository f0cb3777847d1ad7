"""Symmetry search: known shapes get their exact groups, LineMOD matches BOP's models_info."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from argen.models.objects import builtin_objects, info_from_mesh, load_models, surface_scene
from argen.models.symmetry import find_part_symmetry, find_symmetries, rotation_angle_axis, surface_moments

C = trimesh.creation


def _sym(mesh, **kw):
    return find_symmetries(mesh, info_from_mesh(mesh).diameter, **kw)


def _maps_onto_itself(mesh, T, tol):
    """Every vertex of T(mesh) lies within tol (metres) of the mesh's surface."""
    scene = surface_scene(mesh)
    q = trimesh.transform_points(np.asarray(mesh.vertices), T)
    d = scene.compute_distance(o3d.core.Tensor(q.astype(np.float32))).numpy()
    return d.max() < tol


def test_cylinder_has_a_continuous_symmetry_about_its_axis():
    m = C.cylinder(0.03, 0.1, sections=48)
    R = trimesh.transformations.rotation_matrix(0.7, (1, 1, 0))
    m.apply_transform(R)  # the axis is no longer a coordinate axis
    m.apply_translation((0.01, -0.02, 0.005))
    s = _sym(m)
    assert len(s.continuous) == 1 and s.count is None
    axis = R[:3, :3] @ np.array([0, 0, 1.0])
    assert abs(s.continuous[0]["axis"] @ axis) > 0.9999
    # the axis passes through the cylinder's centre
    off = s.continuous[0]["offset"] - np.array([0.01, -0.02, 0.005])
    assert np.linalg.norm(off - (off @ axis) * axis) < 1e-6
    # the two ends are alike: one half turn about a perpendicular axis (BOP composes it with the rotation)
    assert len(s.discrete) == 1
    ang, ax = rotation_angle_axis(s.discrete[0][:3, :3])
    assert ang == pytest.approx(np.pi) and abs(ax @ axis) < 1e-6
    assert _maps_onto_itself(m, s.discrete[0], 2e-4)  # a 48-gon: exact only about vertex or edge axes


def test_box_with_three_different_sides_has_the_three_half_turns():
    m = C.box((0.12, 0.07, 0.03))
    s = _sym(m)
    assert not s.continuous and len(s.discrete) == 3 and s.count == 4
    axes = sorted(tuple(np.round(np.abs(rotation_angle_axis(T[:3, :3])[1]), 6)) for T in s.discrete)
    assert axes == [(0, 0, 1), (0, 1, 0), (1, 0, 0)]
    for T in s.discrete:
        assert rotation_angle_axis(T[:3, :3])[0] == pytest.approx(np.pi)
        assert _maps_onto_itself(m, T, 1e-6)


def test_cube_has_24_symmetries_and_each_maps_it_onto_itself():
    m = C.box((0.05, 0.05, 0.05))
    m.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3)))
    s = _sym(m)
    assert s.count == 24 and not s.continuous
    Rs = [T[:3, :3] for T in s.discrete]
    assert all(abs(np.linalg.det(R) - 1) < 1e-9 for R in Rs)
    assert len({tuple(np.round(R, 6).ravel()) for R in Rs}) == 23  # distinct, identity not listed
    assert all(_maps_onto_itself(m, T, 1e-6) for T in s.discrete)


def test_hexagonal_prism_and_tetrahedron_groups():
    assert _sym(C.cylinder(0.03, 0.02, sections=6)).count == 12  # D6: 6 turns about the axis, 6 half turns
    tet = trimesh.Trimesh([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]],
                          [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]).apply_scale(0.03)
    assert _sym(tet).count == 12  # the tetrahedral rotation group


def test_l_bracket_has_none_and_the_tolerance_decides_near_symmetries():
    bracket = builtin_objects(["bracket"])[0].mesh
    s = _sym(bracket)
    assert s.count == 1 and not s.continuous
    assert 0.05 < s.best_rejected < 0.07  # its flip swaps arms 2 cm apart in length
    loose = _sym(bracket, tol=0.08)  # a looser tolerance accepts that flip
    assert loose.count == 2


def test_surface_moments_are_exact_for_a_box():
    c, M = surface_moments(C.box((0.2, 0.1, 0.1)).apply_translation((1, 2, 3)))
    assert np.allclose(c, (1, 2, 3))
    assert np.allclose(M, np.diag(np.diag(M))) and M[0, 0] > M[1, 1] == pytest.approx(M[2, 2])


def test_linemod_symmetries_match_bop_models_info(lm_models):
    for o in load_models(lm_models):
        s = find_symmetries(o.mesh, o.diameter)
        if o.name in ("eggbox", "glue"):
            assert len(s.discrete) == 1 and not s.continuous, o.name
            # the found transform moves the surface like BOP's listed one, within the tolerance
            v = np.asarray(o.mesh.vertices)
            ours = trimesh.transform_points(v, s.discrete[0])
            bops = trimesh.transform_points(v, o.info.symmetries_discrete[0])
            assert np.linalg.norm(ours - bops, axis=1).max() < s.tol * o.diameter, o.name
        else:
            assert s.count == 1 and not s.continuous, o.name
            assert s.best_rejected > 0.12, o.name


def test_bad_tolerance_is_refused():
    with pytest.raises(ValueError):
        _sym(C.box((0.1, 0.05, 0.02)), tol=1.5)


def _mug(tilt: float = 0.0, shift=(0.0, 0.0, 0.0)):
    """A mug (cylinder r 38 mm, h 95 mm, a torus handle in the xz-plane, tube 7 mm, centre circle r 25 mm at x 45
    mm), turned by ``tilt`` radians about (1, 1, 0) and shifted: its body axis, handle circle centre and the
    transform."""
    m = trimesh.util.concatenate([C.cylinder(0.038, 0.095, sections=48),
                                  C.torus(0.025, 0.007, major_sections=32, minor_sections=12).apply_transform(
                                      trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0))
                                  ).apply_translation((0.045, 0, 0))])
    T = trimesh.transformations.rotation_matrix(tilt, (1, 1, 0))
    T[:3, 3] = shift
    return m.apply_transform(T), T


def test_mug_has_a_part_symmetry_about_its_body_and_its_handle_is_the_odd_part():
    mesh, T = _mug(0.6, (0.01, -0.02, 0.005))
    part = find_part_symmetry(mesh, info_from_mesh(mesh).diameter)
    axis, centre = T[:3, 2], T[:3, 3]
    assert abs(float(part.axis @ axis)) > np.cos(np.radians(1.0))
    assert np.linalg.norm(np.cross(part.offset - centre, axis)) < 0.001  # the axis passes within 1 mm of the body's
    assert 0.75 < part.body < 0.9  # the handle's torus is 18 % of the area
    # every odd point lies on the handle (within the facets' 0.4 mm of the torus), in the body's frame
    local = trimesh.transform_points(part.odd_points, np.linalg.inv(T))
    rho = np.hypot(local[:, 0] - 0.045, local[:, 2])
    assert np.abs(np.hypot(rho - 0.025, local[:, 1]) - 0.007).max() < 0.0006
    assert len(part.odd_points) > 1000
    # each turn maps the body's surface (a sample of the cylinder) onto the mug's surface
    body = trimesh.transform_points(C.cylinder(0.038, 0.095, sections=48).sample(2000, return_index=False), T)
    scene = surface_scene(mesh)
    for R in part.turns()[::5]:
        d = scene.compute_distance(o3d.core.Tensor(trimesh.transform_points(body, R).astype(np.float32))).numpy()
        assert np.quantile(d, 0.99) < 0.001
    assert len(part.turns()) == 35


def test_part_symmetry_is_none_for_symmetric_asymmetric_and_boxy_shapes():
    for mesh in (C.cylinder(0.03, 0.1, sections=48),  # symmetric as a whole: no odd part
                 C.box((0.09, 0.07, 0.03)),  # a box's face turns onto itself about any normal axis, not the rest
                 next(o.mesh for o in builtin_objects(["bracket"]))):
        assert find_part_symmetry(mesh, info_from_mesh(mesh).diameter) is None
    mug, _ = _mug()  # a body share below the minimum
    assert find_part_symmetry(mug, info_from_mesh(mug).diameter, min_body=0.95) is None


def test_part_symmetry_search_is_deterministic():
    mesh, _ = _mug(0.3)
    a, b = (find_part_symmetry(mesh, info_from_mesh(mesh).diameter, seed=3) for _ in range(2))
    assert np.array_equal(a.axis, b.axis) and np.array_equal(a.odd_points, b.odd_points)


def test_ycbv_mug_is_the_only_real_model_with_a_part_symmetry(lm_models, ycbv_real):
    """Of the LineMOD and YCB-Video models at hand only the mug gets one (MIN_BODY's measured margins)."""
    ycbv_models = ycbv_real / "models"
    for models in (lm_models, ycbv_models):
        for o in load_models(models):
            part = find_part_symmetry(o.mesh, o.diameter)
            assert (part is not None) == (o.obj_id == 14 and models == ycbv_models), o.name
            if part is not None:
                assert part.body > 0.9 and abs(part.axis[2]) > 0.99  # the YCB mug stands on its model z axis
