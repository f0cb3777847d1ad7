"""Check a label file against schema v1 and the label invariants (``argen validate``).

Opening checks the schema (argen.h5.LabelFile); then the objects table and every frame are checked:
finite features in the working volume, points on their pixel's ray, unit normals facing the camera,
colours in [0, 1], semantic = the instance's object id, instance rows in range, per-instance point
counts, rotations orthonormal, control points = R corners + t with the box centre last.

Rotation tolerance (:data:`ROT_TOL`): every rotation that argen reads from a BOP file is projected onto SO(3)
(``argen.bop.rotation_from_bop``; real BOP ground truth is off by up to about 2e-3), so a label file's rotations
are exact up to their float32 storage (about 1e-7). 1e-4 leaves room for that rounding and still catches any
rotation that was not projected.
"""

from __future__ import annotations

import os

import numpy as np

from argen.h5 import FrameLabels, LabelFile, ObjectTable

CP_TOL = 1e-5  # metres: float32 rounding of R c + t at a few metres
ROT_TOL = 1e-4  # |R R^T - I|, see the module docstring
RAY_TOL = 0.05  # pixels: a point must project back onto its pixel
UNIT_TOL = 1e-3


def check_objects(o: ObjectTable) -> list[str]:
    """Violations in the objects table."""
    errs = []
    if len(o.ids) == 0:
        errs.append("objects: the table is empty")
    if np.any(np.diff(o.ids) <= 0):
        errs.append("objects: ids are not sorted and unique")
    if len(o.names) != len(o.ids):
        errs.append(f"objects: {len(o.names)} names for {len(o.ids)} ids")
    if not np.all(o.diameters > 0):
        errs.append("objects: non-positive diameter")
    if not np.allclose(o.control_points[:, :8], o.corners, atol=1e-7):
        errs.append("objects: control points 0-7 differ from the corners")
    if not np.allclose(o.control_points[:, 8], o.corners.mean(axis=1), atol=1e-6):
        errs.append("objects: control point 8 is not the box centre")
    for m, s in enumerate(o.sym_transforms):
        if len(s) == 0 or not np.allclose(s[0], np.eye(4), atol=1e-6):
            errs.append(f"objects: symmetry transforms of object {o.ids[m]} do not start with the identity")
        elif o.symmetric[m] != (len(s) > 1):
            errs.append(f"objects: object {o.ids[m]} symmetric flag disagrees with its {len(s)} transforms")
    for m, (turns, odd) in enumerate(zip(o.part_symmetries, o.odd_points)):  # none in files written before them
        turns, odd = np.asarray(turns, np.float64).reshape(-1, 4, 4), np.asarray(odd, np.float64).reshape(-1, 3)
        if (len(turns) == 0) != (len(odd) == 0):
            errs.append(f"objects: object {o.ids[m]} has {len(turns)} part turns and {len(odd)} odd-part points")
            continue
        R = turns[:, :3, :3]
        if len(turns) and (np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > ROT_TOL
                           or np.abs(np.linalg.det(R) - 1).max() > ROT_TOL):
            errs.append(f"objects: a part turn of object {o.ids[m]} is not a rotation")
        lo, hi = o.corners[m].min(axis=0), o.corners[m].max(axis=0)
        if len(odd) and np.any((odd < lo - 1e-4) | (odd > hi + 1e-4)):
            errs.append(f"objects: odd-part points of object {o.ids[m]} lie outside its box")
    return errs


def check_frame(fr: FrameLabels, objects: ObjectTable, max_points: int, max_depth: float) -> list[str]:
    """Violations in one frame (messages without the frame prefix)."""
    errs = []
    n, m = len(fr.features), len(fr.instances)
    f = fr.features
    if n > max_points:
        errs.append(f"{n} points, more than max_points {max_points}")
    if not np.all(np.isfinite(f)):
        return errs + ["non-finite features"]
    z = f[:, 2]
    if np.any(z <= 0) or np.any(z > max_depth * (1 + 1e-6)):
        errs.append(f"points outside the working volume (z in [{z.min():.3f}, {z.max():.3f}] m)")
    h, w = (int(v) for v in fr.image_size)
    r, c = fr.pixel[:, 0], fr.pixel[:, 1]
    if np.any((r < 0) | (r >= h) | (c < 0) | (c >= w)):
        errs.append("pixel outside the image")
    K = fr.cam_K.astype(np.float64)
    zz = np.where(z > 0, z, 1).astype(np.float64)
    u = K[0, 0] * f[:, 0] / zz + K[0, 2]
    v = K[1, 1] * f[:, 1] / zz + K[1, 2]
    if n and (np.abs(u - c).max() > RAY_TOL or np.abs(v - r).max() > RAY_TOL):
        errs.append(f"points do not lie on their pixel's ray (up to {max(np.abs(u - c).max(), np.abs(v - r).max()):.2f} px off)")
    rgb = f[:, 3:6]
    if np.any(rgb < 0) or np.any(rgb > 1):
        errs.append("colours outside [0, 1]")
    nrm = f[:, 6:9]
    if n and np.abs(np.linalg.norm(nrm, axis=1) - 1).max() > UNIT_TOL:
        errs.append("normals are not unit length")
    if n and np.any(np.einsum("ij,ij->i", nrm, f[:, :3]) > 1e-6):
        errs.append("normals facing away from the camera")
    inst = fr.instance
    if np.any((inst < -1) | (inst >= m)):
        return errs + [f"instance index outside [-1, {m})"]
    it = fr.instances
    expect = np.where(inst >= 0, it.obj_id[np.maximum(inst, 0)] if m else 0, 0)
    bad = np.count_nonzero(fr.semantic != expect)
    if bad:
        errs.append(f"{bad} points whose semantic label is not their instance's object id")
    counts = np.bincount(inst[inst >= 0], minlength=m)
    if np.any(counts != it.num_points):
        errs.append("instances/num_points disagree with the points' instance labels")
    if m:
        known = np.isin(it.obj_id, objects.ids)
        if not np.all(known):
            return errs + [f"instance object id(s) {sorted(set(it.obj_id[~known].tolist()))} not in the objects table"]
        R = it.R.astype(np.float64)
        if np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > ROT_TOL or np.any(np.linalg.det(R) < 0):
            errs.append("instance rotation not orthonormal")
        rows = np.array([objects.index(i) for i in it.obj_id])
        cps = objects.control_points[rows].astype(np.float64) @ R.transpose(0, 2, 1) + it.t[:, None, :]
        dev = np.abs(cps - it.control_points).max()
        if dev > CP_TOL:
            errs.append(f"instance control points differ from R corners + t by {dev * 1000:.3f} mm")
        if np.any((it.visib_fract < 0) | (it.visib_fract > 1)):
            errs.append("visib_fract outside [0, 1]")
    return errs


def validate_file(path: str | os.PathLike, max_errors: int = 10) -> tuple[int, list[str]]:
    """Check a label file; returns (frames checked, the first ``max_errors`` violations).

    A file that cannot be opened as schema v1 raises ArgenError.
    """
    errs: list[str] = []
    with LabelFile(path) as lf:
        errs += check_objects(lf.objects)
        max_points, max_depth = int(lf.attrs["max_points"]), float(lf.attrs["max_depth"])
        for i in range(lf.num_frames):
            fr = lf.frame(i)
            errs += [f"frame {i} (scene {fr.scene_id} image {fr.im_id}): {e}"
                     for e in check_frame(fr, lf.objects, max_points, max_depth)]
            if len(errs) >= max_errors:
                return i + 1, errs[:max_errors]
        return lf.num_frames, errs
