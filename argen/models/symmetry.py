"""Rotational symmetries of a mesh, found by search, in BOP's ``models_info.json`` form.

A rigid transformation S is a symmetry of a model with tolerance ``tol`` when it moves the surface by less
than ``tol`` x diameter (BOP's definition; colour is not considered), made robust to scan noise: at least 99 %
of the surface (``quantile``; 1.0 is BOP's strict maximum) must land within ``tol`` x diameter of the
surface. The default tolerance, 5 % of the diameter, is set by what it must tell apart, measured here (99th
percentile of the surface move of the best candidate, fraction of the diameter): the LineMOD scans listed as
symmetric in BOP's models_info.json move by 0.030 (eggbox) and 0.040 (glue); the built-in L-shaped bracket,
whose arms differ by 2 cm, by 0.059; the other six LineMOD objects by at least 0.139. (The strict maximum
does not separate them as well: eggbox 0.057 against the bracket's 0.072, from a few noisy scan points.)

Search: every rotational symmetry fixes the surface's area centroid ``c`` and maps the surface's second-moment
tensor M (about ``c``) onto itself, so its axis runs through ``c`` and

- M with three distinct eigenvalues: the only candidates are the half turns about the three principal axes;
- two equal eigenvalues (one unique axis u): turns of any order about u (or every angle: a continuous
  symmetry), and half turns about axes perpendicular to u;
- three equal eigenvalues (cube, tetrahedron, ...): turns of order 2-6 about the directions from ``c`` to the
  convex hull's vertices, edge midpoints and facets, and about the principal axes.

Candidates are checked with exact point-to-surface distances (open3d's raycasting scene) on seeded surface
samples; the symmetries found are closed under composition. Shapes: transforms (4,4) with translation in the
mesh's units (metres here); axes (3,) unit vectors.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import trimesh
from scipy.optimize import minimize

from argen.models.objects import surface_scene

#: Default tolerance: fraction of the diameter a symmetry may move the surface by.
DEFAULT_TOL = 0.05
#: Share of the surface that must move by less than the tolerance (1.0: every point, BOP's strict rule).
DEFAULT_QUANTILE = 0.99
#: Eigenvalues of the second-moment tensor closer than this fraction of the largest count as equal.
EIGEN_GAP = 0.05
#: Angles (radians) that a continuous symmetry must pass: multiples of 2 pi / 23, which no turn of order
#: up to 12 gives, spread over (0, pi).
CONTINUOUS_ANGLES = tuple(2 * np.pi * k / 23 for k in (3, 1, 7, 5, 11, 9, 2, 4, 6, 8, 10))
MAX_ORDER = 12
MAX_AXES = 240
MAX_GROUP = 120


@dataclass
class Symmetries:
    """What :func:`find_symmetries` found.

    discrete: non-identity (4,4) transforms (translation in the mesh's units); continuous: [{"axis": (3,),
    "offset": (3,)}] (a point on the axis); moved: the largest surface move of each discrete one, as a fraction
    of the diameter; best_rejected: the smallest move among candidates that failed (None if none was tried);
    tol: the tolerance used (fraction of the diameter).
    """

    discrete: list[np.ndarray] = field(default_factory=list)
    continuous: list[dict] = field(default_factory=list)
    moved: list[float] = field(default_factory=list)
    best_rejected: float | None = None
    tol: float = DEFAULT_TOL

    @property
    def count(self) -> int | None:
        """Size of the symmetry group, identity included (None when continuous)."""
        return None if self.continuous else len(self.discrete) + 1

    def describe(self) -> str:
        """One line for the user: what was found and by how much the surface moves."""
        near = "" if self.best_rejected is None else f"; best rejected candidate moves it {self.best_rejected:.1%}"
        if not self.discrete and not self.continuous:
            return f"no symmetry (tolerance {self.tol:.0%} of the diameter{near})"
        parts = []
        for s in self.continuous:
            a = s["axis"]
            parts.append(f"continuous about ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
        if self.discrete:
            turns = []
            for T in self.discrete[:6]:
                ang, ax = rotation_angle_axis(T[:3, :3])
                turns.append(f"{np.degrees(ang):.0f} deg about ({ax[0]:.2f}, {ax[1]:.2f}, {ax[2]:.2f})")
            more = f", ... ({len(self.discrete)} in all)" if len(self.discrete) > 6 else ""
            parts.append(f"{len(self.discrete)} discrete: " + "; ".join(turns) + more)
        worst = f", surface moved at most {max(self.moved):.1%}" if self.moved else ""
        return " + ".join(parts) + f" (tolerance {self.tol:.0%}{worst}{near})"


def rotation_angle_axis(R: np.ndarray) -> tuple[float, np.ndarray]:
    """Angle (radians, 0..pi) and unit axis of a rotation R: (3,3)."""
    ang = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.linalg.norm(w) > 1e-6:
        return ang, w / np.linalg.norm(w)
    # 0 or pi: the axis is the eigenvector of eigenvalue 1
    vals, vecs = np.linalg.eigh((R + R.T) / 2)
    ax = vecs[:, int(np.argmax(vals))]
    ax = ax if ax[np.argmax(np.abs(ax))] > 0 else -ax  # a half turn's axis has no sign: pick one
    return ang, ax / np.linalg.norm(ax)


def turn(axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    """(4,4) rotation by ``angle`` radians about the line through ``centre`` (3,) along ``axis`` (3,)."""
    return trimesh.transformations.rotation_matrix(angle, axis, point=centre)


def surface_moments(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Area centroid c: (3,) and second-moment tensor about it M: (3,3), integrated exactly over the triangles
    (per triangle, the integral of x x^T dA is A/12 (sum_i v_i v_i^T + s s^T), s = v0 + v1 + v2)."""
    tri = np.asarray(mesh.triangles, float)
    area = np.asarray(mesh.area_faces, float)
    total = area.sum()
    c = (area[:, None] * tri.mean(axis=1)).sum(0) / total
    v = tri - c
    s = v.sum(axis=1)
    M = np.einsum("f,fij->ij", area, np.einsum("fvi,fvj->fij", v, v) + np.einsum("fi,fj->fij", s, s)) / 12.0
    return c, M / total


class _Checker:
    """Largest surface move of a transform, as a fraction of the diameter, with an early exit."""

    def __init__(self, mesh: trimesh.Trimesh, diameter: float, n_points: int, seed: int, quantile: float):
        self.scene = surface_scene(mesh)
        pts, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
        self.points = np.asarray(pts, float)
        self.coarse = self.points[:: max(1, n_points // 300)]
        self.diameter = diameter
        self.quantile = quantile

    def distances(self, points: np.ndarray, T: np.ndarray) -> np.ndarray:
        """(N,) the distances (the mesh's units) of T(points) to the surface: points (N,3), T (4,4)."""
        q = np.asarray(points) @ T[:3, :3].T + T[:3, 3]
        return self.scene.compute_distance(o3d.core.Tensor(q.astype(np.float32))).numpy()

    def move(self, T: np.ndarray, limit: float | None = None) -> float:
        """The ``quantile`` of the distances of T(surface samples) to the surface, / diameter; once the coarse
        subset's exceeds ``limit``, that value is returned (enough to reject)."""
        for P in ((self.coarse, self.points) if limit is not None else (self.points,)):
            d = float(np.quantile(self.distances(P, T), self.quantile)) / self.diameter
            if limit is not None and d > limit:
                return d
        return d


def _unique_axes(dirs: np.ndarray, cos_tol: float = np.cos(np.radians(2.0))) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for d in dirs:
        n = np.linalg.norm(d)
        if n < 1e-9:
            continue
        d = d / n
        if all(abs(float(d @ a)) < cos_tol for a in out):
            out.append(d)
    return out


def _hull_directions(mesh: trimesh.Trimesh, c: np.ndarray) -> np.ndarray:
    hull = mesh.convex_hull
    v = np.asarray(hull.vertices) - c
    e = np.asarray(hull.vertices)[hull.edges_unique].mean(axis=1) - c
    f = np.asarray(hull.facets_normal) if len(hull.facets) else np.asarray(hull.face_normals)
    return np.vstack([f, v, e])


def _same(T1: np.ndarray, T2: np.ndarray, scale: float) -> bool:
    return bool(np.abs(T1[:3, :3] - T2[:3, :3]).max() < 1e-3 and np.abs(T1[:3, 3] - T2[:3, 3]).max() < 1e-3 * scale)


def find_symmetries(mesh: trimesh.Trimesh, diameter: float, tol: float = DEFAULT_TOL, n_points: int = 3000,
                    seed: int = 0, quantile: float = DEFAULT_QUANTILE) -> Symmetries:
    """The rotational symmetries of ``mesh`` (any units; diameter in the same units) within ``tol`` x diameter
    (for ``quantile`` of the surface).

    Deterministic for a given seed. A continuous symmetry is reported as BOP does: its axis, plus at most one
    discrete half turn about a perpendicular axis (BOP tools compose the two).
    """
    if not 0 < tol < 1:
        raise ValueError(f"symmetry tolerance must be a fraction of the diameter in (0, 1), got {tol}")
    if not 0.5 <= quantile <= 1:
        raise ValueError(f"symmetry quantile must be in [0.5, 1], got {quantile}")
    chk = _Checker(mesh, diameter, n_points, seed, quantile)
    c, M = surface_moments(mesh)
    lam, V = np.linalg.eigh(M)  # ascending
    gap = EIGEN_GAP * lam[-1]
    eq01, eq12 = lam[1] - lam[0] < gap, lam[2] - lam[1] < gap
    best = [np.inf]
    found: list[np.ndarray] = []
    continuous: list[np.ndarray] = []

    def ok(T: np.ndarray) -> bool:
        m = chk.move(T, limit=tol)
        if m > tol:
            if m < best[0]:  # the coarse subset's value is a lower bound: report the full one
                best[0] = min(best[0], chk.move(T))
            return False
        return True

    def add(T: np.ndarray) -> None:
        if not any(_same(T, S, diameter) for S in found):
            found.append(T)

    def cyclic(axis: np.ndarray, orders=range(MAX_ORDER, 1, -1), try_continuous: bool = True) -> None:
        if try_continuous and all(ok(turn(axis, a, c)) for a in CONTINUOUS_ANGLES):
            if not any(abs(float(axis @ a)) > 0.999 for a in continuous):
                continuous.append(axis)
            return
        # the order whose turns all pass and move the surface least (ties within tol / 5: the larger order);
        # a loose tolerance can let a wrong order's turns pass on a compact shape (a cube's 72-degree turns)
        best_n, best_m = 0, np.inf
        for n in orders:
            if all(ok(turn(axis, 2 * np.pi * k / n, c)) for k in range(1, n // 2 + 1)):
                m = max(chk.move(turn(axis, 2 * np.pi * k / n, c)) for k in range(1, n // 2 + 1))
                if m < best_m - tol / 5:
                    best_n, best_m = n, m
        for k in range(1, best_n):
            add(turn(axis, 2 * np.pi * k / best_n, c))

    if not eq01 and not eq12:  # three distinct eigenvalues: half turns about the principal axes only
        for k in range(3):
            T = turn(V[:, k], np.pi, c)
            if ok(T):
                add(T)
    elif eq01 != eq12:  # one unique axis
        u = V[:, 2] if eq01 else V[:, 0]
        cyclic(u)
        plane = np.vstack([V[:, 0], V[:, 1]] if eq01 else [V[:, 1], V[:, 2]])
        dirs = _hull_directions(mesh, c)
        dirs = dirs - np.outer(dirs @ u, u)
        axes = _unique_axes(np.vstack([plane, dirs]))
        for a in axes[:MAX_AXES]:
            T = turn(a, np.pi, c)
            if ok(T):
                add(T)
                if continuous:  # every perpendicular half turn is one composed with the continuous one
                    break
    else:  # isotropic second moment
        axes = _unique_axes(np.vstack([V.T, _hull_directions(mesh, c)]))
        for a in axes[:MAX_AXES]:
            cyclic(a, orders=range(6, 1, -1))
    # close under composition (a rotation group), checking every product
    if not continuous:
        grew = True
        while grew and len(found) < MAX_GROUP:
            grew = False
            for A in list(found):
                for B in list(found):
                    P = A @ B
                    if np.abs(P[:3, :3] - np.eye(3)).max() < 1e-3 or any(_same(P, S, diameter) for S in found):
                        continue
                    if ok(P):
                        found.append(P)
                        grew = True
    else:  # keep only half turns perpendicular to the (first) continuous axis, at most one
        u = continuous[0]
        flips = [T for T in found if abs(float(rotation_angle_axis(T[:3, :3])[1] @ u)) < 0.1]
        found = flips[:1]
    moved = [chk.move(T) for T in found]
    tidy = lambda x: np.round(x, 9) + 0.0  # noqa: E731  (no 1e-17 noise or -0.0 in models_info.json)
    axes = [tidy(a * (1 if a[np.argmax(np.abs(a))] > 0 else -1)) for a in continuous]
    return Symmetries([tidy(T) for T in found], [{"axis": a, "offset": tidy(c)} for a in axes], moved,
                      None if not np.isfinite(best[0]) else float(best[0]), tol)


# ------------------------------------------------------------------------------------ part symmetries

#: Share of the surface that a part symmetry must keep (within the tolerance) for every turn. Measured (RANSAC axis,
#: 5 % tolerance): the YCB mug keeps 0.955 (its handle is the rest); the LineMOD can, whose spout and handle are
#: large, 0.72; the other LineMOD objects and the YCB gelatin and foam boxes at most 0.52.
MIN_BODY = 0.8
#: A part symmetry's odd part must be at least this share of the surface, else the shape is symmetric as a whole
#: (what :func:`find_symmetries` reports) and any difference is print, not shape.
MIN_ODD = 0.01
#: Turns a part symmetry is taught under: every 10 degrees, as a continuous symmetry is (``argen.label``).
PART_STEPS = 36


@dataclass
class PartSymmetry:
    """An axis about which the surface turns onto itself except for an odd part (a mug's handle): while that part
    is out of sight, every turn about the axis looks the same.

    axis: (3,) unit; offset: (3,) a point on the axis, the mesh's units; body: share of the surface that every turn
    keeps within the tolerance; odd_points: (K,3) surface samples that some turn moves further (the odd part);
    tol: the tolerance (fraction of the diameter).
    """

    axis: np.ndarray
    offset: np.ndarray
    body: float
    odd_points: np.ndarray
    tol: float = DEFAULT_TOL

    def turns(self, steps: int = PART_STEPS) -> np.ndarray:
        """(steps-1, 4, 4) float64: the turns by k x 360/steps degrees about the axis, k = 1..steps-1."""
        return np.stack([turn(self.axis, 2 * np.pi * k / steps, self.offset) for k in range(1, steps)])

    def describe(self) -> str:
        a, c = np.round(self.axis, 2) + 0.0, np.round(self.offset, 6) + 0.0  # no "-0.00"
        return (f"turns about ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f}) through ({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g}) keep "
                f"{self.body:.0%} of the surface (tolerance {self.tol:.0%}); the rest is the odd part")


def _rotation_field(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Rows [p x n, n] (N,6): the surface is turned onto itself about the axis (a, through c) when every point's
    velocity a x (p - c) is tangent, n . (a x p) + n . (c x a) = 0, which is linear in (a, c x a) (Pottmann and
    Randrup's kinematic surfaces)."""
    return np.hstack([np.cross(points, normals), normals])


def _axis_from(x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(axis (3,) unit, its point nearest the origin (3,)) of the velocity field x = (a, m), its translation along
    the axis dropped (a screw's pitch); None for a pure translation field."""
    a, m = x[:3], x[3:]
    na = float(np.linalg.norm(a))
    if na < 1e-9:
        return None
    a, m = a / na, m / na
    m = m - (a @ m) * a
    return a, np.cross(a, m)


def _tangent_residual(points: np.ndarray, normals: np.ndarray, a: np.ndarray, c: np.ndarray):
    """Per point: |sin| of the angle between the turn's velocity and the tangent plane (N,), the velocity's length
    (N,) and whether the normal runs along the axis (N,) bool (a face across the axis turns onto itself anywhere)."""
    v = np.cross(a, points - c)
    nv = np.linalg.norm(v, axis=1)
    r = np.abs(np.einsum("ij,ij->i", normals, v)) / np.maximum(nv, 1e-12)
    return r, nv, np.abs(normals @ a) > 0.995


def _fit_axis(rows: np.ndarray, nv: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares velocity field of the rows (each divided by its velocity's length: an angle, not a distance)."""
    if len(rows) < 6:
        return None
    return _axis_from(np.linalg.svd(rows / np.maximum(nv, 1e-12)[:, None], full_matrices=False)[2][-1])


def _worst_move(chk: _Checker, points: np.ndarray, a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Per point (N,): the largest distance to the surface, as a fraction of the diameter, over the turns about the
    axis by ``CONTINUOUS_ANGLES``."""
    worst = np.zeros(len(points))
    for ang in CONTINUOUS_ANGLES:
        worst = np.maximum(worst, chk.distances(points, turn(a, ang, c)) / chk.diameter)
    return worst


def _polish_axis(chk: _Checker, body: np.ndarray, a: np.ndarray, c: np.ndarray,
                 tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The axis near (a, c) that moves the body's points (B,3) least: the mean distance to the surface (each capped
    at ``tol`` x diameter) of the points turned by 90, 180 and 270 degrees, minimised by Nelder-Mead over the
    axis's two tilts and its two shifts across itself. The normals' least-squares fit is biased by scan noise near
    the axis and by a part's points that happen to be tangent; this is the symmetry's own test."""
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    cap = tol * chk.diameter
    sample = body[:: max(1, len(body) // 1500)]

    def axis_of(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = a + x[0] * e1 + x[1] * e2
        return u / np.linalg.norm(u), c + (x[2] * e1 + x[3] * e2) * chk.diameter

    def cost(x: np.ndarray) -> float:
        u, o = axis_of(x)
        return sum(float(np.minimum(chk.distances(sample, turn(u, ang, o)), cap).mean())
                   for ang in (np.pi / 2, np.pi, 3 * np.pi / 2))

    res = minimize(cost, np.zeros(4), method="Nelder-Mead",
                   options={"initial_simplex": np.vstack([np.zeros(4), 0.02 * np.eye(4)]), "xatol": 1e-4,
                            "fatol": 1e-7 * chk.diameter, "maxiter": 400})
    return axis_of(res.x)


def find_part_symmetry(mesh: trimesh.Trimesh, diameter: float, tol: float = DEFAULT_TOL, min_body: float = MIN_BODY,
                       n_points: int = 3000, n_odd: int = 50000, iterations: int = 300,
                       seed: int = 0) -> PartSymmetry | None:
    """The axis about which turns keep the most of the surface, when they keep at least ``min_body`` of it and no
    more than ``1 - MIN_ODD``; else None. Units: the mesh's (diameter in the same).

    Search: an axis turns a surface onto itself where the turn's velocity at each point is tangent to it, a linear
    condition on the axis (:func:`_rotation_field`). RANSAC on surface samples with their face normals (8 per try,
    ``iterations`` seeded tries, each refit to the normals it explains) finds axes the most normals agree with,
    whatever the odd part does; each of the four best distinct ones is checked with exact distances (as
    :func:`find_symmetries` checks), and one that comes near ``min_body`` is polished on its body's points
    (:func:`_polish_axis`). Odd points: of ``n_odd`` surface samples, those some turn moves by more than ``tol`` x
    diameter (at most 4000 kept, seeded).
    """
    if not 0 < tol < 1:
        raise ValueError(f"symmetry tolerance must be a fraction of the diameter in (0, 1), got {tol}")
    pts, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    P, N = np.asarray(pts, float), np.asarray(mesh.face_normals, float)[face]
    rows = _rotation_field(P, N)
    rng = np.random.default_rng(seed)
    tries = []
    for _ in range(iterations):
        got = _axis_from(np.linalg.svd(rows[rng.choice(len(P), 8, replace=False)])[2][-1])
        if got is None:
            continue
        for _ in range(3):  # refit to the points it explains
            r, nv, along = _tangent_residual(P, N, *got)
            fit = (r < 0.1) & ~along & (nv > 1e-3 * diameter)
            better = _fit_axis(rows[fit], nv[fit])
            if better is None:
                break
            got = better
        r, nv, along = _tangent_residual(P, N, *got)
        tries.append((float(np.mean((r < 0.1) | along)), *got))
    tries.sort(key=lambda x: -x[0])
    chk = _Checker(mesh, diameter, n_points, seed, 1.0)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    distinct: list[tuple[np.ndarray, np.ndarray]] = []
    for _, a, c in tries:
        if any(abs(float(a @ b)) > 0.996 and np.linalg.norm(np.cross(c - d, b)) < 0.01 * diameter for b, d in distinct):
            continue
        distinct.append((a, c))
        worst = _worst_move(chk, P, a, c)
        body = float(np.mean(worst < tol))
        if body >= min_body - 0.1:  # worth polishing: the axis that moves its body least
            a, c = _polish_axis(chk, P[worst < tol], a, c, tol)
            body = float(np.mean(_worst_move(chk, P, a, c) < tol))
        if best is None or body > best[0]:
            best = (body, a, c)
        if len(distinct) == 4:
            break
    if best is None or not min_body <= best[0] <= 1 - MIN_ODD:
        return None
    body, a, c = best
    dense = np.asarray(trimesh.sample.sample_surface(mesh, n_odd, seed=seed + 1)[0], float)
    odd = dense[_worst_move(chk, dense, a, c) >= tol]
    if len(odd) < MIN_ODD * n_odd:
        return None
    if len(odd) > 4000:
        odd = odd[np.sort(np.random.default_rng(seed).choice(len(odd), 4000, replace=False))]
    a = a if a[np.argmax(np.abs(a))] > 0 else -a
    c = c - (c @ a) * a  # the axis's point nearest the mesh origin
    return PartSymmetry(np.round(a, 9) + 0.0, np.round(c, 12) + 0.0, body, odd, tol)


_FOUND: dict[tuple, PartSymmetry | None] = {}


def part_symmetry_of(mesh: trimesh.Trimesh, diameter: float) -> PartSymmetry | None:
    """:func:`find_part_symmetry` with its defaults, remembered for the process by the mesh's vertices and faces: a
    second label file of the same models does not search again (a few seconds a model with a part symmetry)."""
    key = (hashlib.sha1(np.ascontiguousarray(mesh.vertices, np.float64).tobytes()
                        + np.ascontiguousarray(mesh.faces, np.int64).tobytes()).hexdigest(), float(diameter))
    if key not in _FOUND:
        _FOUND[key] = find_part_symmetry(mesh, diameter)
    return _FOUND[key]
