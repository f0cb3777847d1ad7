"""Distractor objects: procedural household things of realistic shape and size, and their placement.

Real scenes are full of things that are not the targets: mugs, cups, bowls, bottles, cans, boxes, books,
tools, toys, cables, fruit, keyboards, laptops. A detector trained among plain boxes and cylinders calls such things
targets, so capture-sim scatters these instead. Every shape is generated here from trimesh primitives
(revolved profiles, swept tubes, boxes), at its real size in metres, standing on z = 0 in a stable resting
pose with its footprint centred on the origin. Shapes are generated, not taken from a mesh package, because
no maintained package on PyPI ships a licence-clear household set that installs without a download at run
time (pybullet_data's YCB-like objects are a few toys, robosuite pulls in MuJoCo); generation also gives
unlimited variety in proportions and colours from one seed.

A *library* is a fixed list of such meshes made once per process from a fixed seed (so the renderer's mesh
cache stays bounded); each frame picks from it, scales each pick by a small factor and turns it about z.
Distractors are background: they are rendered with seg_id 0 and never carry a target label.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh

from argen.sim.placement import beside, convex_hull_2d, separation

#: Household colours (sRGB 0-255) drawn for distractors: whites, greys, blacks, woods and saturated paints,
#: reds included (targets are often red; a red mug among them forces the detector to use shape).
PALETTE = np.array([
    [235, 235, 230], [200, 200, 195], [140, 140, 140], [70, 70, 75], [25, 25, 28], [120, 85, 55], [170, 130, 90],
    [200, 40, 35], [150, 20, 25], [230, 120, 30], [240, 200, 40], [60, 140, 60], [30, 90, 50], [40, 90, 170],
    [20, 40, 100], [120, 60, 150], [230, 150, 170], [90, 170, 190], [180, 170, 140], [110, 30, 10],
], dtype=np.float64)


def _colour(rng: np.random.Generator) -> np.ndarray:
    c = PALETTE[int(rng.integers(len(PALETTE)))] * rng.uniform(0.8, 1.15)
    return np.clip(c + rng.normal(0, 10, 3), 0, 255)


def paint(mesh: trimesh.Trimesh, rng: np.random.Generator, printed: bool = False, cell: float = 0.015) -> trimesh.Trimesh:
    """Give ``mesh`` vertex colours: one colour with a light speckle, or (``printed``) a print-like pattern.

    The printed pattern (packaging, book covers, magazines) is blocks of ``cell`` metres in 2-4 colours, so
    the mesh is first subdivided to edges of at most ``cell``. Returns the painted mesh (a new object).
    """
    if printed:
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=cell)
        mesh = trimesh.Trimesh(v, f, process=False)
        cols = np.stack([_colour(rng) for _ in range(int(rng.integers(2, 5)))])
        shift = rng.uniform(0, cell, 3)
        block = np.floor((mesh.vertices + shift) / (cell * rng.uniform(1, 4, 3))).astype(np.int64)
        idx = (block[:, 0] * 7 + block[:, 1] * 13 + block[:, 2] * 29) % len(cols)
        rgb = cols[idx] + rng.normal(0, 8, (len(idx), 3))
    else:
        mesh = mesh.copy()
        rgb = _colour(rng) + rng.normal(0, 8, (len(mesh.vertices), 3))
    rgba = np.c_[np.clip(rgb, 0, 255).astype(np.uint8), np.full(len(rgb), 255, np.uint8)]
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba)
    return mesh


def _revolve(profile: list[tuple[float, float]], sections: int = 32) -> trimesh.Trimesh:
    """A solid of revolution about z from a (radius, z) polyline that starts and ends on the axis (metres)."""
    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    return m


def _rod(length: float, radius: float, axis: str = "x", centre=(0.0, 0.0, 0.0), sections: int = 16) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    if axis == "x":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    elif axis == "y":
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    m.apply_translation(centre)
    return m


def _cup_profile(r_bottom: float, r_top: float, h: float, wall: float) -> list[tuple[float, float]]:
    """Open-topped thin-walled vessel (cup, mug, glass, pot), base on z = 0."""
    return [(0, 0), (r_bottom, 0), (r_top, h), (r_top - wall, h), (r_bottom - wall, wall), (0, wall)]


def mug(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = rng.uniform(0.035, 0.05), rng.uniform(0.08, 0.11)
    body = _revolve(_cup_profile(r * rng.uniform(0.85, 1.0), r, h, 0.005))
    handle = trimesh.creation.torus(major_radius=h * 0.28, minor_radius=0.006, major_sections=24, minor_sections=8)
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([r + h * 0.12, 0, h * 0.5])
    return paint(trimesh.util.concatenate([body, handle]), rng)


def cup(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = rng.uniform(0.03, 0.045), rng.uniform(0.07, 0.15)
    return paint(_revolve(_cup_profile(r * rng.uniform(0.6, 0.9), r, h, 0.003)), rng)


def bowl(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = rng.uniform(0.06, 0.11), rng.uniform(0.045, 0.08)
    a = np.linspace(0, np.pi / 2, 8)
    outer = [(r * 0.45 + (r - r * 0.45) * np.sin(t), h * (1 - np.cos(t))) for t in a]
    inner = [(x - 0.005, max(z, 0.006)) for x, z in outer[::-1]]
    return paint(_revolve([(0, 0), *outer, *inner, (0, 0.006)]), rng)


def bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = rng.uniform(0.03, 0.045), rng.uniform(0.18, 0.3)
    neck = rng.uniform(0.011, 0.016)
    shoulder = h * rng.uniform(0.6, 0.75)
    return paint(_revolve([(0, 0), (r, 0), (r, shoulder), (neck, shoulder + h * 0.12), (neck, h),
                           (0, h)]), rng)


def can(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = rng.uniform(0.026, 0.05), rng.uniform(0.07, 0.14)
    return paint(_revolve([(0, 0), (r * 0.92, 0), (r, 0.006), (r, h - 0.006), (r * 0.92, h), (0, h)]), rng,
                 printed=bool(rng.random() < 0.5))


def lying(mesh_fn: Callable) -> Callable:
    """A builder for ``mesh_fn``'s shape lying on its side (bottles and cans roll over on desks)."""
    def build(rng: np.random.Generator) -> trimesh.Trimesh:
        m = mesh_fn(rng)
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        return m
    build.__name__ = f"lying_{mesh_fn.__name__}"
    return build


def box(rng: np.random.Generator) -> trimesh.Trimesh:
    e = np.sort(rng.uniform([0.03, 0.05, 0.08], [0.08, 0.15, 0.3]))
    e = rng.permutation(e) if rng.random() < 0.5 else e[[1, 0, 2]]
    return paint(_box(e, (0, 0, e[2] / 2)), rng, printed=bool(rng.random() < 0.7))


def books(rng: np.random.Generator) -> trimesh.Trimesh:
    """A stack of one to three books lying flat, slightly askew."""
    parts, z = [], 0.0
    for _ in range(int(rng.integers(1, 4))):
        e = (rng.uniform(0.13, 0.25), rng.uniform(0.1, 0.18), rng.uniform(0.01, 0.045))
        b = _box(e, (0, 0, e[2] / 2))
        b.apply_transform(trimesh.transformations.rotation_matrix(rng.normal(0, 0.15), [0, 0, 1]))
        b.apply_translation([*rng.normal(0, 0.01, 2), z])
        parts.append(paint(b, rng, printed=True, cell=0.02))
        z += e[2]
    return trimesh.util.concatenate(parts)


def screwdriver(rng: np.random.Generator) -> trimesh.Trimesh:
    lh, rh = rng.uniform(0.08, 0.11), rng.uniform(0.012, 0.018)
    ls = rng.uniform(0.07, 0.15)
    handle = paint(_rod(lh, rh, "x", (0, 0, rh)), rng)
    shaft = paint(_rod(ls, 0.003, "x", (lh / 2 + ls / 2, 0, rh)), rng)
    return trimesh.util.concatenate([handle, shaft])


def hammer(rng: np.random.Generator) -> trimesh.Trimesh:
    lh = rng.uniform(0.22, 0.3)
    head = (rng.uniform(0.09, 0.12), 0.025, 0.025)
    handle = paint(_rod(lh, 0.013, "y", (0, 0, 0.0125)), rng)
    top = paint(_box(head, (0, lh / 2, 0.0125)), rng)
    return trimesh.util.concatenate([handle, top])


def toy_car(rng: np.random.Generator) -> trimesh.Trimesh:
    L, W = rng.uniform(0.08, 0.16), rng.uniform(0.04, 0.07)
    wr = W * 0.22
    body = paint(_box((L, W, L * 0.2), (0, 0, wr + L * 0.1)), rng)
    cabin = paint(_box((L * 0.5, W * 0.85, L * 0.15), (-L * 0.05, 0, wr + L * 0.2 + L * 0.075)), rng)
    wheels = [paint(_rod(W * 0.2, wr, "y", (sx * L * 0.32, sy * W * 0.45, wr)), rng) for sx in (-1, 1) for sy in (-1, 1)]
    return trimesh.util.concatenate([body, cabin, *wheels])


def blocks(rng: np.random.Generator) -> trimesh.Trimesh:
    """Toy building blocks: two to four cubes stacked or side by side."""
    parts, x = [], 0.0
    for _ in range(int(rng.integers(2, 5))):
        s = rng.uniform(0.025, 0.05)
        if rng.random() < 0.5 and parts:
            top = max(p.bounds[1, 2] for p in parts)
            parts.append(paint(_box((s, s, s), (x - s / 2, rng.normal(0, 0.004), top + s / 2)), rng))
        else:
            parts.append(paint(_box((s, s, s), (x + s / 2, 0, s / 2)), rng))
            x += s
    return trimesh.util.concatenate(parts)


def fruit(rng: np.random.Generator) -> trimesh.Trimesh:
    r = rng.uniform(0.03, 0.045)
    m = trimesh.creation.icosphere(subdivisions=2, radius=r)
    m.apply_scale([1, rng.uniform(0.9, 1.1), rng.uniform(0.8, 1.0)])
    m.apply_translation([0, 0, -m.bounds[0, 2]])
    return paint(m, rng)


def cable(rng: np.random.Generator) -> trimesh.Trimesh:
    """A cable lying on the desk: a thin tube along a smooth random curve."""
    n = 40
    turn = np.cumsum(rng.normal(0, 0.25, n))
    step = rng.uniform(0.01, 0.015)
    path = np.c_[np.cumsum(np.cos(turn)) * step, np.cumsum(np.sin(turn)) * step, np.full(n, 0.0035)]
    return paint(tube(path, 0.0035), rng)


def tube(path: np.ndarray, radius: float, sides: int = 8) -> trimesh.Trimesh:
    """A closed tube of ``radius`` metres along ``path`` (N,3) metres (horizontal steps), capped at both ends."""
    n = len(path)
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.cross([0.0, 0.0, 1.0], tangent)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    up = np.cross(tangent, side)
    a = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = (np.cos(a)[None, :, None] * side[:, None] + np.sin(a)[None, :, None] * up[:, None]) * radius
    v = (path[:, None] + ring).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(sides), indexing="ij")
    a0, a1 = i * sides + j, i * sides + (j + 1) % sides
    b0, b1 = a0 + sides, a1 + sides
    faces = np.r_[np.c_[a0.ravel(), a1.ravel(), b1.ravel()], np.c_[a0.ravel(), b1.ravel(), b0.ravel()]]
    v = np.r_[v, path[[0, -1]]]
    c0, c1 = len(v) - 2, len(v) - 1
    caps = [[c0, (k + 1) % sides, k] for k in range(sides)] + \
           [[c1, (n - 1) * sides + k, (n - 1) * sides + (k + 1) % sides] for k in range(sides)]
    m = trimesh.Trimesh(v, np.r_[faces, caps], process=True)
    trimesh.repair.fix_normals(m)
    return m


def bar_keyboard(rng: np.random.Generator) -> trimesh.Trimesh:
    """A keyboard drawn coarsely: a slab with five bars for its key rows (no separate keys; see :func:`keyboard`)."""
    L, W = rng.uniform(0.35, 0.45), rng.uniform(0.12, 0.16)
    base = paint(_box((L, W, 0.018), (0, 0, 0.009)), rng)
    keys = [_box((L * 0.92, W * 0.14, 0.008), (0, (k - 2) * W * 0.18, 0.022)) for k in range(5)]
    return trimesh.util.concatenate([base, paint(trimesh.util.concatenate(keys), rng)])


def _key_grid(width: float, depth: float, rows: int, pitch: float, cap: float, z: float, top: float,
              space: bool = True) -> list[trimesh.Trimesh]:
    """Key caps in ``rows`` rows of ``pitch`` metres filling ``width`` x ``depth`` (centred on the origin), each a
    box ``cap`` x ``cap`` x ``top`` metres standing on height ``z``; with ``space``, the row nearest the user (-y)
    has a space bar."""
    caps = []
    cols = max(int(width // pitch), 1)
    x0 = -(cols - 1) * pitch / 2
    for r in range(rows):
        y = -depth / 2 + pitch / 2 + r * pitch
        if r == 0 and space and cols > 6:  # modifiers, a space bar of six keys' width, modifiers
            side = (cols - 6) // 2
            xs = [x0 + c * pitch for c in range(side)] + [x0 + c * pitch for c in range(side + 6, cols)]
            caps.append(_box((6 * pitch - (pitch - cap), cap, top), (x0 + (side + 2.5) * pitch, y, z + top / 2)))
        else:
            xs = [x0 + c * pitch for c in range(cols)]
        caps += [_box((cap, cap, top), (x, y, z + top / 2)) for x in xs]
    return caps


def keyboard(rng: np.random.Generator) -> trimesh.Trimesh:
    """A computer keyboard: a low case with separate key caps on a 19 mm pitch (5-6 rows, a space bar), standing
    6-10 mm proud of it, and on wide ones a number pad beside the main block. Real keyboards lie beside
    the objects on most desks; their rows of small bumps look to a depth network like the bumps of small objects."""
    rows = int(rng.integers(5, 7))
    pitch = rng.uniform(0.018, 0.0195)
    main = rng.uniform(14.5, 15.5) * pitch
    pad = 4 * pitch + 0.02 if rng.random() < 0.5 else 0.0
    L, W = main + pad + rng.uniform(0.015, 0.04), rows * pitch + rng.uniform(0.015, 0.05)
    h = rng.uniform(0.012, 0.022)
    base = paint(_box((L, W, h), (0, 0, h / 2)), rng)
    cap, top = pitch * rng.uniform(0.75, 0.88), rng.uniform(0.006, 0.01)
    caps = _key_grid(main, rows * pitch, rows, pitch, cap, h, top)
    for c in caps:
        c.apply_translation([-pad / 2, 0, 0])
    if pad:
        numpad = _key_grid(4 * pitch, rows * pitch, rows, pitch, cap, h, top, space=False)
        for c in numpad:
            c.apply_translation([main / 2 + 0.02 + 2 * pitch - pad / 2, 0, 0])
        caps += numpad
    return trimesh.util.concatenate([base, paint(trimesh.util.concatenate(caps), rng)])


def laptop(rng: np.random.Generator) -> trimesh.Trimesh:
    """An open laptop: a flat base with low key caps and a touch pad, its lid hinged at the back edge (+y) and
    opened 95-130 degrees."""
    W, D, h = rng.uniform(0.3, 0.38), rng.uniform(0.21, 0.26), rng.uniform(0.014, 0.022)
    base = paint(_box((W, D, h), (0, 0, h / 2)), rng)
    pitch = W * 0.88 / 15
    caps = _key_grid(W * 0.88, 5 * pitch, 5, pitch, pitch * 0.82, h, 0.0015)
    for c in caps:
        c.apply_translation([0, D / 2 - 5 * pitch / 2 - 0.02, 0])
    pad = _box((W * 0.3, D * 0.25, 0.001), (0, -D / 2 + D * 0.16, h + 0.0005))
    t = rng.uniform(0.005, 0.009)
    lid = _box((W, t, D), (0, 0, D / 2))
    lid.apply_transform(trimesh.transformations.rotation_matrix(-rng.uniform(0.09, 0.7), [1, 0, 0]))
    lid.apply_translation([0, D / 2 - t / 2, h])
    return trimesh.util.concatenate([base, paint(trimesh.util.concatenate([*caps, pad]), rng), paint(lid, rng)])


def mouse(rng: np.random.Generator) -> trimesh.Trimesh:
    """A computer mouse: a half ellipsoid, 10-12 cm long, 6-6.5 cm wide and 3-4 cm high."""
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    v = m.vertices.copy()
    v[:, 2] = np.maximum(v[:, 2], 0.0)
    m = trimesh.Trimesh(v * [rng.uniform(0.03, 0.0325), rng.uniform(0.05, 0.06), rng.uniform(0.03, 0.04)],
                        m.faces, process=False)
    return paint(m, rng)


def monitor(rng: np.random.Generator) -> trimesh.Trimesh:
    """A flat screen on a stand, the screen's face towards -y."""
    W, H = rng.uniform(0.45, 0.6), rng.uniform(0.28, 0.36)
    lift = rng.uniform(0.08, 0.15)
    foot = paint(_box((0.2, 0.16, 0.015), (0, 0.04, 0.0075)), rng)
    neck = paint(_box((0.05, 0.03, lift + H / 2), (0, 0.05, (lift + H / 2) / 2)), rng)
    screen = paint(_box((W, 0.025, H), (0, 0.02, lift + H / 2)), rng)
    return trimesh.util.concatenate([foot, neck, screen])


#: Builders of small things, by kind; each draws its proportions and colours from the generator.
SMALL: dict[str, Callable] = {f.__name__: f for f in (
    mug, cup, bowl, bottle, can, box, books, screwdriver, hammer, toy_car, blocks, fruit, cable, bar_keyboard,
    lying(bottle), lying(can))}
#: Large things that stand on the desk behind the board.
LARGE: dict[str, Callable] = {"monitor": monitor}
#: Computer things that lie on the desk beside the board (``clutter.desk_things``).
DESK: dict[str, Callable] = {f.__name__: f for f in (keyboard, laptop, mouse)}

_cache: dict = {}


def centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """``mesh`` moved so that it stands on z = 0 with its footprint's box centred on the origin."""
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def _made(builders: dict[str, Callable], variants: int, seed: int) -> list[tuple[str, trimesh.Trimesh]]:
    """``variants`` meshes of every kind in ``builders`` from one generator of ``seed``, as (kind, mesh) pairs,
    standing on z = 0 with their footprints centred; made once per process."""
    key = (tuple(builders), variants, seed)
    if key not in _cache:
        rng = np.random.default_rng(seed)
        _cache[key] = [(kind, centred(fn(rng))) for kind, fn in builders.items() for _ in range(variants)]
    return _cache[key]


def library(variants: int = 4, seed: int = 2024) -> list[tuple[str, trimesh.Trimesh]]:
    """The process's fixed distractor set: ``variants`` meshes of every small kind, as (kind, mesh) pairs.

    Meshes are in metres at their real size, standing on z = 0, footprint centred. Made once per process.
    """
    return _made(SMALL, variants, seed)


def large_library(variants: int = 3, seed: int = 2025) -> list[tuple[str, trimesh.Trimesh]]:
    """Like :func:`library`, for the large kinds (monitors)."""
    return _made(LARGE, variants, seed)


def desk_library(variants: int = 4, seed: int = 2026) -> list[tuple[str, trimesh.Trimesh]]:
    """Like :func:`library`, for the computer things (keyboards with separate keys, laptops, mice)."""
    return _made(DESK, variants, seed)


def hull_footprint(mesh: trimesh.Trimesh, T: np.ndarray) -> np.ndarray:
    """(K,2) convex footprint on the z = 0 plane of ``mesh`` (metres) posed by ``T`` (4,4, may scale)."""
    v = _hull_vertices(mesh) @ T[:3, :3].T + T[:3, 3]
    return convex_hull_2d(v[:, :2])


def _hull_vertices(mesh: trimesh.Trimesh) -> np.ndarray:
    """(V,3) convex-hull vertices of ``mesh``, cached per mesh object: the entry keeps the mesh itself, so its id()
    cannot be reused by another mesh while the entry exists."""
    key = ("hull", id(mesh))
    if key not in _cache or _cache[key][0] is not mesh:
        _cache[key] = (mesh, np.asarray(mesh.convex_hull.vertices))
    return _cache[key][1]


def pose(scale: float, yaw: float, xyz) -> np.ndarray:
    """(4,4) transform: uniform ``scale``, a turn of ``yaw`` radians about z, then a shift to ``xyz`` metres."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) * scale
    T[:3, 3] = xyz
    return T


#: A distractor whose sorted box extents all lie within this factor of a target's is a look-alike of it.
LOOKALIKE = 1.25


def lookalike(extents: np.ndarray, targets: np.ndarray, factor: float = LOOKALIKE) -> bool:
    """Whether a shape of box ``extents`` (3,) metres could pass for one of ``targets`` (T,3) box extents.

    A distractor labelled background that has a target's size and build teaches the detector that the target
    itself is background (a generic box or mug target among box or mug distractors of its size), so such
    shapes are not placed. Compared sorted, so any orientation counts.
    """
    if len(targets) == 0:
        return False
    r = np.sort(extents)[None, :] / np.sort(targets, axis=1)
    return bool(np.any(np.all((r < factor) & (r > 1 / factor), axis=1)))


def place_on(region: Callable[[np.random.Generator], np.ndarray], inside: Callable[[np.ndarray], bool],
             z: float, shapes: list, count: int, taken: list[np.ndarray], rng: np.random.Generator,
             scale: tuple[float, float] = (0.85, 1.2), near: list[np.ndarray] | None = None,
             near_prob: float = 0.0, tries: int = 40, avoid: np.ndarray | None = None
             ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Place up to ``count`` shapes standing on the plane at height ``z`` (metres), without overlaps.

    region(rng) -> (2,) a candidate centre; inside(footprint (K,2)) -> whether the footprint lies on the
    surface. shapes: (kind, mesh) pairs to draw from. taken: footprints already on this surface (appended to).
    near: footprints (targets) that a shape is put right next to with probability ``near_prob`` (gap 0-1 cm).
    avoid: (T,3) box extents (metres) of the targets: no :func:`lookalike` of them is placed.
    Returns (shape index, T (4,4), footprint (K,2)) for each placed shape.
    """
    out = []
    for _ in range(count):
        for _ in range(tries):
            i = int(rng.integers(len(shapes)))
            mesh = shapes[i][1]
            k = rng.uniform(*scale)
            if avoid is not None and lookalike(mesh.extents * k, avoid):
                continue
            T = pose(k, rng.uniform(0, 2 * np.pi), (0.0, 0.0, z))
            fp0 = hull_footprint(mesh, T)
            if near and rng.random() < near_prob:
                a = rng.uniform(0, 2 * np.pi)
                xy = beside(near[int(rng.integers(len(near)))], fp0, np.array([np.cos(a), np.sin(a)]),
                            rng.uniform(0.001, 0.01))
            else:
                xy = region(rng)
            T[:2, 3] = xy
            fp = fp0 + xy
            if not inside(fp) or any(separation(fp, o) <= 0.0 for o in taken):
                continue
            taken.append(fp)
            out.append((i, T, fp))
            break
    return out
