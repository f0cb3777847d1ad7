"""Distractors and the room of capture-sim's scenes: real invariants of the placement, over many seeds.

- a distractor is background (seg_id 0): it never carries a target label;
- no two things on a surface intersect: targets and distractors alike (checked in 3D on the meshes' hulls,
  independently of the footprint test that placement uses);
- every distractor rests on a surface: its lowest point lies on the plane and its footprint inside the outline.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay

from argen.config import TemplateConfig, load_template
from argen.models.objects import builtin_objects
from argen.sim import distractors
from argen.sim.board import Board
from argen.sim.scene import build_scene

SEEDS = range(8)


@pytest.fixture(scope="module", params=["default", "desk_things"])
def scenes(request):
    """The linemod template's scenes, as they are and with computer things on the desk (``clutter.desk_things``)."""
    cfg = load_template("linemod")
    if request.param == "desk_things":
        cfg = dataclasses.replace(cfg, clutter=dataclasses.replace(cfg.clutter, desk_things=(1, 3)))
    board = Board.from_config(cfg.board)
    objs = builtin_objects()
    return cfg, board, [build_scene(cfg, objs, board, np.random.default_rng(s)) for s in SEEDS]


def _world_vertices(mesh, T) -> np.ndarray:
    return np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3]


def _solids(scene):
    """(name, world hull vertices, world surface samples) of every target and distractor."""
    out = []
    meshes = [(f"target {p.obj.name}", p.obj.mesh, p.T_world_obj) for p in scene.placements]
    meshes += [(f"distractor {d['kind']}", scene.background[d["item"]].mesh, scene.background[d["item"]].T_world_obj)
               for d in scene.info["distractors"]]
    for name, mesh, T in meshes:
        samples = np.r_[np.asarray(mesh.vertices)[::max(1, len(mesh.vertices) // 150)],
                        trimesh.sample.sample_surface(mesh, 150, seed=0)[0]]
        out.append((name, _world_vertices(mesh.convex_hull, T), samples @ T[:3, :3].T + T[:3, 3]))
    return out


def test_every_shape_kind_is_a_real_sized_solid_standing_on_z0():
    lib = distractors.library(variants=2)
    assert {k for k, _ in lib} == set(distractors.SMALL)
    for kind, mesh in lib:
        lo, hi = mesh.bounds
        assert abs(lo[2]) < 1e-9, kind
        assert np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-9), kind
        assert 0.02 < (hi - lo).max() < 0.6, (kind, hi - lo)  # household sizes, metres
        assert mesh.visual.kind == "vertex" and len(mesh.visual.vertex_colors) == len(mesh.vertices), kind


def test_computer_things_are_real_sized_solids_standing_on_z0():
    lib = distractors.desk_library(variants=2)
    assert {k for k, _ in lib} == set(distractors.DESK)
    for kind, mesh in lib:
        lo, hi = mesh.bounds
        assert abs(lo[2]) < 1e-9 and np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-9), kind
        assert 0.05 < (hi - lo).max() < 0.5 and (hi - lo)[2] < 0.3, (kind, hi - lo)


def test_a_keyboard_has_separate_keys_standing_proud_of_its_case():
    """Each key cap is its own solid (the coarse bar keyboard has one bar a row): 60-110 caps, a space bar, and the
    caps' tops 6-10 mm above the case."""
    rng = np.random.default_rng(3)
    for _ in range(6):
        parts = distractors.keyboard(rng).split(only_watertight=False)
        case = max(parts, key=lambda p: p.area)
        caps = [p for p in parts if p is not case]
        assert 60 <= len(caps) <= 110
        widths = sorted(p.extents[0] for p in caps)
        assert widths[-1] > 4 * widths[len(widths) // 2]  # the space bar
        proud = np.array([p.bounds[1, 2] for p in caps]) - case.bounds[1, 2]
        assert np.all((proud > 0.0059) & (proud < 0.0101))
    assert len(distractors.bar_keyboard(rng).split(only_watertight=False)) == 6


def test_computer_things_lie_beside_the_board_only_when_asked_for(scenes):
    cfg, board, built = scenes
    kinds = [d["kind"] for s in built for d in s.info["distractors"] if d["surface"] == "desk"]
    things = [k for k in kinds if k in distractors.DESK]
    if cfg.clutter.desk_things == (0, 0):
        assert not things
        return
    assert len(things) >= len(built) and {"keyboard", "laptop"} <= set(things)
    # most of them right beside the board (within 5 cm of its edge), where the camera sees them
    from argen.sim.placement import separation

    half = board.side / 2
    square = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    gaps = [separation(distractors.hull_footprint(s.background[d["item"]].mesh, s.background[d["item"]].T_world_obj),
                       square) for s in built for d in s.info["distractors"] if d["kind"] in distractors.DESK]
    assert np.mean(np.array(gaps) < 0.05) > 0.5


def test_scenes_have_distractors_on_the_board_and_the_desk(scenes):
    cfg, _, built = scenes
    on_board = [sum(d["surface"] == "board" for d in s.info["distractors"]) for s in built]
    on_desk = [sum(d["surface"] == "desk" for d in s.info["distractors"]) for s in built]
    assert max(on_board) >= 2 and sum(on_board) >= len(built)
    assert min(on_desk) >= cfg.clutter.count[0] // 2
    assert len({d["kind"] for s in built for d in s.info["distractors"]}) >= 12


def test_distractors_are_background_never_targets(scenes):
    _, _, built = scenes
    for s in built:
        assert all(it.seg_id == 0 for it in s.background)
        assert [it.seg_id for it in s.object_items()] == list(range(1, len(s.placements) + 1))


def intersections(scene) -> tuple[list[tuple[str, str]], int]:
    """Pairs of things whose surface points lie inside the other's hull (shrunk by 0.01 % so that touching faces
    do not count), and the number of pairs close enough to be checked."""
    solids = _solids(scene)
    hulls = [Delaunay(h) for _, h, _ in solids]
    bad, checked = [], 0
    for i, (name_i, _, v_i) in enumerate(solids):
        for j, (name_j, h_j, _) in enumerate(solids):
            if i == j or np.any(v_i.max(0) < h_j.min(0)) or np.any(v_i.min(0) > h_j.max(0)):
                continue
            checked += 1
            c = v_i.mean(0)
            if (hulls[j].find_simplex(c + (v_i - c) * (1 - 1e-4)) >= 0).any():
                bad.append((name_i, name_j))
    return bad, checked


def test_nothing_intersects_a_target_or_another_distractor(scenes):
    _, _, built = scenes
    checked = 0
    for s in built:
        bad, n = intersections(s)
        assert not bad
        checked += n
    assert checked > 20


def test_the_intersection_check_finds_a_distractor_moved_into_a_target(scenes):
    _, _, built = scenes
    s = next(s for s in built if any(d["surface"] == "board" for d in s.info["distractors"]))
    d = next(d for d in s.info["distractors"] if d["surface"] == "board")
    item = s.background[d["item"]]
    moved = item.T_world_obj.copy()
    moved[:2, 3] = s.placements[0].T_world_obj[:2, 3]
    s2 = copy.copy(s)
    s2.background = list(s.background)
    s2.background[d["item"]] = dataclasses.replace(item, T_world_obj=moved)
    assert intersections(s2)[0]


def test_every_distractor_rests_on_its_surface(scenes):
    _, _, built = scenes
    for s in built:
        surfaces = {name: (z, outline) for name, z, outline in s.surfaces}
        for d in s.info["distractors"]:
            it = s.background[d["item"]]
            z, outline = surfaces[d["surface"]]
            v = _world_vertices(it.mesh, it.T_world_obj)
            assert abs(v[:, 2].min() - z) < 1e-6, (d, v[:, 2].min(), z)
            lo, hi = outline.min(0) - 1e-9, outline.max(0) + 1e-9
            assert np.all(v[:, :2] >= lo) and np.all(v[:, :2] <= hi), d


def test_targets_stand_close_together(scenes):
    """With placement.beside, many frames have two targets within 2.5 cm of each other."""
    from argen.sim.placement import separation

    _, _, built = scenes
    close = 0
    for s in built:
        fps = [p.footprint for p in s.placements]
        close += any(separation(a, b) < 0.025 for k, a in enumerate(fps) for b in fps[k + 1:])
    assert close >= len(built) // 3


def test_scene_is_a_pure_function_of_the_seed():
    cfg = TemplateConfig()
    board = Board.from_config(cfg.board)
    objs = builtin_objects()
    a = build_scene(cfg, objs, board, np.random.default_rng(5))
    b = build_scene(cfg, objs, board, np.random.default_rng(5))
    assert [it.key for it in a.background] == [it.key for it in b.background]
    assert all(np.array_equal(x.T_world_obj, y.T_world_obj) for x, y in zip(a.background, b.background))


def _library_distractors(scene):
    """(distractor info, box extents (3,) metres as placed) of each distractor drawn from the library (papers and the
    large kinds left out)."""
    for d in scene.info["distractors"]:
        it = scene.background[d["item"]]
        if d["kind"] != "papers" and it.key[0] == "distractor":
            yield d, it.mesh.extents * np.cbrt(np.linalg.det(it.T_world_obj[:3, :3]))


def test_no_distractor_is_a_lookalike_of_a_target(scenes):
    """Labels never contradict: nothing labelled background has a target's size and build."""
    _, _, built = scenes
    targets = np.array([o.mesh.extents for o in builtin_objects()])
    for s in built:
        for d, ext in _library_distractors(s):
            assert not distractors.lookalike(ext, targets), d
    # the rule itself: a 10 % larger copy of a target is a look-alike, a 40 % larger one or a flat one is not
    assert distractors.lookalike(targets[0] * 1.1, targets)
    assert not distractors.lookalike(targets[0] * 1.4, targets)
    assert not distractors.lookalike(targets[0] * [1.0, 1.0, 0.3], targets[:1])


def test_a_template_may_place_lookalikes():
    """``clutter.avoid_lookalikes: false`` places distractors of a target's size (never labelled: background), the
    same scenes with the default place none."""
    cfg = load_template("linemod")
    board = Board.from_config(cfg.board)
    objs = builtin_objects()
    targets = np.array([o.mesh.extents for o in objs])
    free = dataclasses.replace(cfg, clutter=dataclasses.replace(cfg.clutter, avoid_lookalikes=False))

    def lookalikes(c) -> int:
        n = 0
        for seed in SEEDS:
            s = build_scene(c, objs, board, np.random.default_rng(seed))
            assert all(s.background[d["item"]].seg_id == 0 for d in s.info["distractors"])
            n += sum(distractors.lookalike(ext, targets) for _, ext in _library_distractors(s))
        return n

    assert lookalikes(cfg) == 0
    assert lookalikes(free) > 0


def test_caches_never_serve_a_freed_objects_geometry():
    """Boards and meshes made one after another, each freed before the next (so Python may reuse an address):
    every board's mesh has its own side and every hull footprint is its own mesh's. Caches keyed by id() failed
    this and made a capture's bytes depend on what the process had made before."""
    import gc

    from argen.config import BoardConfig
    from argen.sim.scene import board_mesh

    for i in range(8):
        board = Board.from_config(BoardConfig() if i % 2 else BoardConfig(markers_per_side=7, marker_size=0.03,
                                                                            marker_gap=0.015, margin=0.005))
        side = board.side
        assert np.allclose(board_mesh(board).extents[:2], side, atol=1e-6)
        del board
        mesh = trimesh.creation.box((0.05 + 0.02 * i, 0.04, 0.03))
        fp = distractors.hull_footprint(mesh, np.eye(4))
        assert np.allclose(np.ptp(fp, axis=0), [0.05 + 0.02 * i, 0.04], atol=1e-9)
        del mesh
        gc.collect()
