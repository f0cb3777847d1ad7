"""One frame's virtual world: table, marker board, desk clutter, lights and the placed objects.

World frame = board frame (origin at the board centre on its top surface, z up). The background
(table, board, clutter) is what a real sensor would see; the placed objects are the virtual ones
that the AR step renders from the marker-estimated camera pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from argen.config import TemplateConfig
from argen.models.objects import ObjectModel
from argen.sim.board import Board
from argen.sim.placement import Placement, choose_instances, convex_hull_2d, place_instances, separation
from argen.sim.render import Light, RenderItem, textured_plane

N_CLUTTER_SHAPES = 24


@dataclass
class Scene:
    """background: table, board and clutter items; placements: the virtual objects (seg_id = index + 1)."""

    background: list[RenderItem]
    placements: list[Placement]
    unplaced: list[str]
    lights: list[Light]
    ambient: float
    info: dict = field(default_factory=dict)

    def object_items(self) -> list[RenderItem]:
        """Render items of the placed objects, seg_id = 1 + index into ``placements``."""
        return [RenderItem(key=("obj", p.obj.source, p.obj.obj_id), mesh=p.obj.mesh, T_world_obj=p.T_world_obj, seg_id=i + 1)
                for i, p in enumerate(self.placements)]


_cache: dict = {}


def _speckled(mesh: trimesh.Trimesh, rgb, rng: np.random.Generator, speckle: float = 12.0) -> trimesh.Trimesh:
    cols = np.clip(np.asarray(rgb, float) + rng.normal(0, speckle, (len(mesh.vertices), 3)), 0, 255)
    cols = np.c_[cols.astype(np.uint8), np.full(len(cols), 255, np.uint8)]
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=cols)
    return mesh


def clutter_library() -> list[trimesh.Trimesh]:
    """Fixed set of clutter shapes (boxes, cylinders, spheres, cones) of unit largest size, base at z=0.

    Made once per process from a fixed seed, so render caches stay bounded; each frame picks shapes
    and scales them uniformly.
    """
    if "clutter" not in _cache:
        rng = np.random.default_rng(2024)
        shapes = []
        for i in range(N_CLUTTER_SHAPES):
            kind = i % 4
            if kind == 0:
                m = trimesh.creation.box(rng.uniform(0.3, 1.0, 3))
            elif kind == 1:
                m = trimesh.creation.cylinder(rng.uniform(0.15, 0.5), rng.uniform(0.3, 1.0), sections=24)
            elif kind == 2:
                m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
                m.apply_scale(rng.uniform(0.4, 1.0, 3))
            else:
                m = trimesh.creation.cone(rng.uniform(0.2, 0.5), rng.uniform(0.4, 1.0), sections=24)
            m.apply_scale(1.0 / m.extents.max())
            m.apply_translation([0, 0, -m.bounds[0, 2]])
            shapes.append(_speckled(m, rng.integers(30, 240, 3), rng))
        _cache["clutter"] = shapes
    return _cache["clutter"]


def table_mesh(size: float, color) -> trimesh.Trimesh:
    """A table slab of ``size`` metres, top surface at z=0, slightly speckled."""
    key = ("table", size, tuple(color))
    if key not in _cache:
        m = trimesh.creation.box((size, size, 0.03))
        m = m.subdivide().subdivide()
        m.apply_translation([0, 0, -0.015])
        _cache[key] = _speckled(m, color, np.random.default_rng(7), speckle=10.0)
    return _cache[key]


def board_mesh(board: Board) -> trimesh.Trimesh:
    """The board as a textured slab, top surface at z=0."""
    key = ("board", id(board))
    if key not in _cache:
        _cache[key] = textured_plane(board.side, board.texture(), thickness=board.cfg.thickness)
    return _cache[key]


def _clutter_footprint(shape: trimesh.Trimesh, T: np.ndarray) -> np.ndarray:
    v = shape.convex_hull.vertices @ T[:3, :3].T + T[:3, 3]
    return convex_hull_2d(v[:, :2])


def _clutter_pose(scale: float, yaw: float, xy) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * scale
    T[:2, 3] = xy
    return T


def build_scene(cfg: TemplateConfig, objects: list[ObjectModel], board: Board, rng: np.random.Generator) -> Scene:
    """Draw one frame's scene: placed objects, clutter around (and optionally on) the board, lights."""
    half = board.side / 2
    table_top = -board.cfg.thickness
    items = [
        RenderItem(key=("table", cfg.scene.table_size), mesh=table_mesh(cfg.scene.table_size, cfg.scene.table_color),
                   T_world_obj=_translate(0, 0, table_top), seg_id=0),
        RenderItem(key=("board",), mesh=board_mesh(board), T_world_obj=np.eye(4), seg_id=0),
    ]
    # objects on the board's free area
    instances = choose_instances(objects, cfg.placement, rng)
    placements, failed = place_instances(instances, cfg.placement, board.free_half_extent, rng)
    taken = [p.footprint for p in placements]
    # distractors on the board (occluders, lchf) and clutter on the table around it
    lib = clutter_library()
    board_square = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    n_on = cfg.clutter.on_board
    n_around = int(rng.integers(cfg.clutter.count[0], cfg.clutter.count[1] + 1))
    for k in range(n_on + n_around):
        on_board = k < n_on
        for _ in range(50):
            shape_i = int(rng.integers(len(lib)))
            scale = rng.uniform(*cfg.clutter.size) * (0.6 if on_board else 1.0)
            yaw = rng.uniform(0, 2 * np.pi)
            if on_board:
                xy = rng.uniform(-board.free_half_extent, board.free_half_extent, 2)
            else:
                r, a = rng.uniform(*cfg.clutter.ring), rng.uniform(0, 2 * np.pi)
                xy = r * np.array([np.cos(a), np.sin(a)])
            T = _clutter_pose(scale, yaw, xy)
            fp = _clutter_footprint(lib[shape_i], T)
            if on_board:
                if np.abs(fp).max() > board.free_half_extent or any(separation(fp, o) < 0.0 for o in taken):
                    continue
            else:
                if separation(fp, board_square) < 0.005 or any(separation(fp, o) < 0.0 for o in taken):
                    continue
            T[2, 3] = 0.0 if on_board else table_top
            items.append(RenderItem(key=("clutter", shape_i), mesh=lib[shape_i], T_world_obj=T, seg_id=0))
            taken.append(fp)
            break
    lights = _lights(cfg, rng)
    info = {"placed": [p.obj.name for p in placements], "unplaced": [o.name for o in failed],
            "clutter": len(items) - 2}
    return Scene(items, placements, [o.name for o in failed], lights, cfg.scene.ambient, info)


def _translate(x, y, z) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _lights(cfg: TemplateConfig, rng: np.random.Generator) -> list[Light]:
    """A directional 'sun' from a random direction above, and a point light above the board."""
    el = rng.uniform(np.deg2rad(35), np.deg2rad(85))
    az = rng.uniform(0, 2 * np.pi)
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])  # towards the light
    # pyrender lights shine along their node's -z: z axis = d
    z = d
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T_sun = np.eye(4)
    T_sun[:3, :3] = np.stack([x, y, z], axis=1)
    T_point = _translate(*rng.uniform(-0.5, 0.5, 2), rng.uniform(1.0, 2.0))
    return [
        Light("directional", float(rng.uniform(*cfg.scene.light_intensity)), np.ones(3), T_sun),
        Light("point", float(rng.uniform(*cfg.scene.point_light_intensity)), np.ones(3), T_point),
    ]
