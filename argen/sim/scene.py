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
from argen.sim import distractors as distractors_mod
from argen.sim.board import Board
from argen.sim.placement import Placement, choose_instances, convex_hull_2d, place_instances, separation
from argen.sim.render import Light, RenderItem, textured_plane


@dataclass
class Scene:
    """background: room, board and distractor items; placements: the virtual objects (seg_id = index + 1).

    surfaces: the horizontal planes things stand on, as (name, z metres, (K,2) outline); info["distractors"]
    lists each distractor as {"kind", "surface", "item"} with ``item`` its index into ``background``.
    """

    background: list[RenderItem]
    placements: list[Placement]
    unplaced: list[str]
    lights: list[Light]
    ambient: float
    info: dict = field(default_factory=dict)
    surfaces: list = field(default_factory=list)

    def object_items(self) -> list[RenderItem]:
        """Render items of the placed objects, seg_id = 1 + index into ``placements``."""
        return [RenderItem(key=("obj", p.obj.source, p.obj.obj_id), mesh=p.obj.mesh, T_world_obj=p.T_world_obj, seg_id=i + 1)
                for i, p in enumerate(self.placements)]


_cache: dict = {}

#: Surface textures drawn per frame: (kind, base colours sRGB). Desks: woods, white, greys, black laminate;
#: floors: carpet and wood; walls: paints.
DESK_COLOURS = [(150, 110, 70), (190, 150, 100), (110, 75, 45), (225, 225, 220), (160, 160, 160), (90, 90, 95),
                (45, 45, 50), (200, 190, 170)]
FLOOR_COLOURS = [(120, 110, 95), (80, 80, 85), (150, 120, 90), (60, 50, 45), (170, 160, 150)]
WALL_COLOURS = [(235, 235, 225), (220, 215, 200), (200, 210, 215), (180, 180, 175), (230, 220, 190), (150, 160, 150)]
TEXTURE_VARIANTS = 3
COVER_LIFT = 0.0005  # metres: a cover's top above the board (the objects' lowest half millimetre sinks in it)


def surface_texture(colour, grain: str, seed: int, px: int = 256) -> np.ndarray:
    """(px, px, 3) uint8 procedural texture: ``grain`` "wood" (streaks), "carpet" (fine noise) or "paint"."""
    rng = np.random.default_rng(seed)
    base = np.asarray(colour, np.float64)
    if grain == "wood":
        rows = np.cumsum(rng.normal(0, 1, px))
        streak = np.sin(np.linspace(0, rng.uniform(20, 60), px)[:, None] + rows[None, :] * 0.05)
        tex = base * (1 + 0.12 * streak[..., None]) + rng.normal(0, 4, (px, px, 3))
    elif grain == "carpet":
        tex = base * rng.uniform(0.75, 1.25, (px, px, 1)) + rng.normal(0, 12, (px, px, 3))
    else:
        tex = base + rng.normal(0, 3, (px, px, 3))
    return np.clip(tex, 0, 255).astype(np.uint8)


def _slab(name: str, colours: list, grain: str, rng: np.random.Generator) -> tuple[tuple, trimesh.Trimesh]:
    """One of a fixed set of unit slabs (1 x 1 x 1 m, top at z = 0, textured top): (render key, mesh)."""
    i = int(rng.integers(len(colours) * TEXTURE_VARIANTS))
    key = ("surface", name, grain, i)  # the key names everything the texture depends on (render cache)
    if key not in _cache:
        tex = surface_texture(colours[i // TEXTURE_VARIANTS], grain, seed=1000 * len(name) + i)
        _cache[key] = textured_plane(1.0, tex, thickness=1.0)
    return key, _cache[key]


def box_pose(centre, extents, R: np.ndarray | None = None) -> np.ndarray:
    """(4,4) pose of a unit slab (top face at z = 0) scaled to ``extents`` (x, y, thickness) metres, its top
    face's centre at ``centre``, turned by R (3,3) (default: none)."""
    T = np.eye(4)
    T[:3, :3] = (np.eye(3) if R is None else R) @ np.diag(extents)
    T[:3, 3] = centre
    return T


def board_key(board: Board) -> tuple:
    """The cache key of ``board``'s mesh (here and in the renderer): its config, all the mesh depends on. Not its
    id(): a board freed and another made at the same address would get the first one's mesh."""
    return ("board", repr(board.cfg))


def board_mesh(board: Board) -> trimesh.Trimesh:
    """The board as a textured slab, top surface at z=0."""
    key = board_key(board)
    if key not in _cache:
        _cache[key] = textured_plane(board.side, board.texture(), thickness=board.cfg.thickness)
    return _cache[key]


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)


def _within(outline: np.ndarray):
    lo, hi = outline.min(0), outline.max(0)
    return lambda fp: bool(np.all(fp >= lo) and np.all(fp <= hi))


def build_room(cfg: TemplateConfig, board: Board, rng: np.random.Generator) -> tuple[list[RenderItem], dict]:
    """The desk under the board (random extent: its edges may be in view), the floor below and walls.

    Returns the render items and {"desk": (4,2) outline metres, "desk_z", "walls": [((2,) outward unit normal,
    distance of the wall's face from the board centre, metres)]}.
    """
    sc = cfg.scene
    half = board.side / 2
    top = -board.cfg.thickness
    x0, x1, y0, y1 = (-half - rng.uniform(*sc.table_margin), half + rng.uniform(*sc.table_margin),
                      -half - rng.uniform(*sc.table_margin), half + rng.uniform(*sc.table_margin))
    height = rng.uniform(*sc.table_height)
    items = []
    key, mesh = _slab("desk", DESK_COLOURS, "wood" if rng.random() < 0.4 else "paint", rng)
    items.append(RenderItem(key, mesh, box_pose(((x0 + x1) / 2, (y0 + y1) / 2, top), (x1 - x0, y1 - y0, 0.03))))
    key, mesh = _slab("floor", FLOOR_COLOURS, "carpet" if rng.random() < 0.6 else "wood", rng)
    items.append(RenderItem(key, mesh, box_pose((0, 0, top - height), (8.0, 8.0, 0.02))))
    edges = [x1, -x0, y1, -y0]  # distance of each desk edge from the board centre: +x, -x, +y, -y
    normals = [np.array(n, float) for n in ((1, 0), (-1, 0), (0, 1), (0, -1))]
    walls = []
    for e in rng.permutation(4)[: int(rng.integers(sc.walls[0], sc.walls[1] + 1))]:
        d = edges[e] + rng.uniform(*sc.wall_gap)
        n = normals[e]  # outward; the wall faces -n
        up, face = np.array([0.0, 0.0, 1.0]), np.r_[-n, 0.0]
        R = np.stack([np.cross(up, face), up, face], axis=1)
        key, mesh = _slab("wall", WALL_COLOURS, "paint", rng)
        front = np.r_[n * d, top - height + 1.25]  # the wall's face, 2.5 m high from the floor, 5 cm thick
        items.append(RenderItem(key, mesh, box_pose(front, (4.0, 2.5, 0.05), R)))
        walls.append((n, float(d)))
    return items, {"desk": _rect(x0, x1, y0, y1), "desk_z": top, "walls": walls}


def build_scene(cfg: TemplateConfig, objects: list[ObjectModel], board: Board, rng: np.random.Generator) -> Scene:
    """Draw one frame's scene: room, placed objects, distractors among them, on the desk and on a shelf, lights."""
    half = board.side / 2
    cl = cfg.clutter
    items, room = build_room(cfg, board, rng)
    items.append(RenderItem(key=board_key(board), mesh=board_mesh(board), T_world_obj=np.eye(4), seg_id=0))
    board_square = _rect(-half, half, -half, half)
    surfaces = [("board", 0.0, board_square), ("desk", room["desk_z"], room["desk"])]
    if rng.random() < cl.board_cover:  # a magazine, cloth or mat over the free area; the markers stay visible
        f = board.free_half_extent + board.cfg.marker_gap / 2
        key, mesh = _paper(rng) if rng.random() < 0.5 else _slab("cover", DESK_COLOURS + FLOOR_COLOURS, "carpet", rng)
        yaw = rng.normal(0, 0.05)
        items.append(RenderItem(key, mesh, box_pose((0, 0, COVER_LIFT), (2 * f * np.cos(yaw) - 0.01, 2 * f * np.cos(yaw) - 0.01, 1e-4),
                                                   distractors_mod.pose(1.0, yaw, (0, 0, 0))[:3, :3])))
    distractors = []

    def add(kind: str, key, mesh, T, surface: str) -> None:
        distractors.append({"kind": kind, "surface": surface, "item": len(items)})
        items.append(RenderItem(key=key, mesh=mesh, T_world_obj=T, seg_id=0))

    # targets on the board's free area, then distractors among them
    instances = choose_instances(objects, cfg.placement, rng)
    placements, failed = place_instances(instances, cfg.placement, board.free_half_extent, rng)
    targets = [p.footprint for p in placements]
    lib = distractors_mod.library()
    # no look-alikes of any target object, unless the template places them
    avoid = np.array([o.mesh.extents for o in objects]).reshape(-1, 3) if cl.avoid_lookalikes else None
    f = board.free_half_extent
    n_on = int(rng.integers(cl.on_board[0], cl.on_board[1] + 1))
    for i, T, _ in distractors_mod.place_on(lambda r: r.uniform(-f, f, 2), _within(_rect(-f, f, -f, f)), 0.0, lib,
                                            n_on, list(targets), rng, cl.scale, near=targets, near_prob=cl.near_target,
                                            avoid=avoid):
        add(lib[i][0], ("distractor", i), lib[i][1], T, "board")
    # the desk around the board: papers first (flat), a monitor, computer things, then the small things
    desk_in = _within(room["desk"])

    def on_desk(fp: np.ndarray) -> bool:
        return desk_in(fp) and separation(fp, board_square) > 0.005

    def ring(r: np.random.Generator) -> np.ndarray:
        d, a = r.uniform(*cl.ring), r.uniform(0, 2 * np.pi)
        return d * np.array([np.cos(a), np.sin(a)])

    dz = room["desk_z"]
    taken: list[np.ndarray] = []
    for _ in range(int(rng.integers(cl.papers[0], cl.papers[1] + 1))):
        e = (rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.42), 0.003)
        key, mesh = _paper(rng)
        T = box_pose((0, 0, dz + e[2]), e, distractors_mod.pose(1.0, rng.uniform(0, 2 * np.pi), (0, 0, 0))[:3, :3])
        for _ in range(20):
            T[:2, 3] = ring(rng)
            fp = distractors_mod.hull_footprint(mesh, T)
            if on_desk(fp) and not any(separation(fp, o) <= 0 for o in taken):
                taken.append(fp)
                add("papers", key, mesh, T, "desk")
                break
    big = distractors_mod.large_library()
    if rng.random() < cl.monitor:
        for i, T, fp in distractors_mod.place_on(lambda r: ring(r) * 1.2, on_desk, dz, big, 1, taken, rng, (1.0, 1.0)):
            # turn the screen (its face is -y) towards the board centre
            yaw = np.arctan2(-T[1, 3], -T[0, 3]) + np.pi / 2
            T2 = distractors_mod.pose(1.0, yaw, T[:3, 3])
            fp2 = distractors_mod.hull_footprint(big[i][1], T2)
            if on_desk(fp2) and not any(separation(fp2, o) <= 0 for o in taken[:-1]):
                taken[-1] = fp2
                add(big[i][0], ("large", i), big[i][1], T2, "desk")
            else:
                taken.pop()
    if cl.desk_things[1] > 0:  # drawn only when asked for, so that captures without them stay as they were
        things = distractors_mod.desk_library()
        n = int(rng.integers(cl.desk_things[0], cl.desk_things[1] + 1))
        # mostly right beside the board, as a keyboard lies beside the things on a desk (and in view of the camera)
        for i, T, _ in distractors_mod.place_on(ring, on_desk, dz, things, n, taken, rng, (0.95, 1.05),
                                                near=[board_square], near_prob=0.8, avoid=avoid):
            add(things[i][0], ("desk_thing", i), things[i][1], T, "desk")
    n_desk = int(rng.integers(cl.count[0], cl.count[1] + 1))
    for i, T, _ in distractors_mod.place_on(ring, on_desk, dz, lib, n_desk, taken, rng, cl.scale, avoid=avoid):
        add(lib[i][0], ("distractor", i), lib[i][1], T, "desk")
    # a shelf on one wall, above the desk, with things on it
    if room["walls"] and rng.random() < cl.shelf:
        n, d = room["walls"][int(rng.integers(len(room["walls"])))]
        depth, width = rng.uniform(0.2, 0.3), rng.uniform(0.6, 1.2)
        z = dz + rng.uniform(0.45, 0.7)
        t = np.array([-n[1], n[0]])
        c = n * (d - depth / 2) + t * rng.uniform(-0.3, 0.3)
        outline = convex_hull_2d(np.array([c + sa * t * width / 2 + sb * n * depth / 2 for sa in (-1, 1) for sb in (-1, 1)]))
        high = [d["item"] for d in distractors if _top(items[d["item"]]) > z - 0.03]
        if not any(separation(outline, distractors_mod.hull_footprint(items[i].mesh, items[i].T_world_obj)) <= 0
                   for i in high):
            key, mesh = _slab("shelf", DESK_COLOURS, "wood", rng)
            R = distractors_mod.pose(1.0, np.arctan2(n[1], n[0]), (0, 0, 0))[:3, :3]
            items.append(RenderItem(key, mesh, box_pose((*c, z), (depth, width, 0.02), R)))
            surfaces.append(("shelf", z, outline))
            lo, hi = outline.min(0), outline.max(0)
            for i, T, _ in distractors_mod.place_on(lambda r: r.uniform(lo, hi), _within(outline), z, lib,
                                                    int(rng.integers(cl.shelf_items[0], cl.shelf_items[1] + 1)), [],
                                                    rng, cl.scale, avoid=avoid):
                add(lib[i][0], ("distractor", i), lib[i][1], T, "shelf")
    lights = draw_lights(cfg, rng)
    info = {"placed": [p.obj.name for p in placements], "unplaced": [o.name for o in failed],
            "clutter": len(distractors), "distractors": distractors}
    return Scene(items, placements, [o.name for o in failed], lights, float(rng.uniform(*cfg.scene.ambient)), info,
                 surfaces)


def _top(item: RenderItem) -> float:
    """Highest z (metres) of a render item's mesh in the world."""
    v = item.mesh.bounds
    corners = np.array([[x, y, z, 1.0] for x in v[:, 0] for y in v[:, 1] for z in v[:, 2]])
    return float((corners @ item.T_world_obj.T)[:, 2].max())


def _paper(rng: np.random.Generator) -> tuple[tuple, trimesh.Trimesh]:
    """A magazine or printed sheet: a unit slab with a print-like texture (blocks of colour, text-like rows)."""
    i = int(rng.integers(8))
    key = ("paper", i)
    if key not in _cache:
        r = np.random.default_rng(500 + i)
        tex = np.full((256, 256, 3), r.integers(200, 250), np.float64)
        for _ in range(int(r.integers(2, 6))):  # pictures
            a, b = sorted(r.integers(0, 256, 2)), sorted(r.integers(0, 256, 2))
            tex[a[0]:a[1], b[0]:b[1]] = r.integers(0, 255, 3)
        for row in range(8, 256, 9):  # text lines
            if r.random() < 0.6:
                c0 = int(r.integers(0, 60))
                tex[row:row + 3, c0:c0 + int(r.integers(60, 190))] *= 0.35
        tex = np.clip(tex + r.normal(0, 6, tex.shape), 0, 255).astype(np.uint8)
        _cache[key] = textured_plane(1.0, tex, thickness=1.0)
    return key, _cache[key]


def _translate(x, y, z) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def draw_lights(cfg: TemplateConfig, rng: np.random.Generator) -> list[Light]:
    """A directional 'sun' from a random direction above and point lights above the board (world z up), each slightly
    warm or cool (``scene.light_tint``)."""
    sc = cfg.scene
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

    def tint() -> np.ndarray:
        w = rng.uniform(-sc.light_tint, sc.light_tint)  # > 0 warm, < 0 cool
        return np.clip(np.array([1 + w, 1.0, 1 - w]) + rng.normal(0, sc.light_tint / 4, 3), 0, None)

    lights = [Light("directional", float(rng.uniform(*sc.light_intensity)), tint(), T_sun)]
    for _ in range(int(rng.integers(sc.point_lights[0], sc.point_lights[1] + 1))):
        T_point = _translate(*rng.uniform(-0.8, 0.8, 2), rng.uniform(0.8, 2.0))
        lights.append(Light("point", float(rng.uniform(*sc.point_light_intensity)), tint(), T_point))
    return lights
