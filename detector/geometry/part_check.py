"""Which turn about its body: an object whose surface turns onto itself about an axis but for an odd part (a mug's
handle: ``argen.models.symmetry.find_part_symmetry``) gets, from points that do not show that part, a pose whose
turn about the axis nothing in those points decides (a stage 2 taught so, ``detector.stage2.crops.PartTurns``, says
as much). The frame's depth still rules turns out: where the odd part would stand in front of what the sensor saw
behind it, or would be in plain sight and is not there, the turn is wrong. :func:`part_checked` poses each such
detection in every turn of its part symmetry (``ObjectInfo.part_symmetries``) and keeps the one whose odd part the
frame sees, if any; else the pose as it is when the frame allows it; else the middle of the widest run of turns
whose odd part it contradicts least: the odd part hidden behind the body or something in front, the middle of where
it can hide. Numpy; metres; poses map
model into camera points (``x_cam = R @ x_model + t``).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from detector.geometry.icp import refine_turned, support_radius, turned_poses
from detector.geometry.verify import RangeImage, depth_votes

#: The odd part counts as in sight under a turn when the frame sees this share of its points more than it sees
#: through them.
PART_SEEN = 0.2
#: Turns whose share of odd points seen through is within this of the least are the ones the frame allows.
PART_SLACK = 0.05
#: The check looks at about this many of the odd part's samples, evenly spread over them (the shares above need no
#: more; each is looked up in every turn).
PART_POINTS = 400


def part_turn(seen: np.ndarray, through: np.ndarray, n_points: int) -> int:
    """The turn to keep, of K evenly spaced turns about the axis in order (0 = the pose itself): the one the frame
    sees the odd part under, (seen - through) / n_points at least ``PART_SEEN``; else the pose itself when the
    frame allows it (its seen-through share within ``PART_SLACK`` of the least: whatever told stage 2 its turn, the
    frame does not contradict it); else the middle of the longest circular run of allowed turns (ties: the first).
    seen, through: (K,) counts of the odd part's n_points (:func:`detector.geometry.verify.depth_votes`)."""
    seen, through = np.asarray(seen, np.float64), np.asarray(through, np.float64)
    n = max(int(n_points), 1)
    gain = (seen - through) / n
    best = int(np.argmax(gain))
    if gain[best] >= PART_SEEN:
        return best
    ok = through / n <= (through / n).min() + PART_SLACK
    if ok[0]:  # the frame allows the pose as it is: nothing to correct
        return 0
    k = len(ok)
    start = int(np.flatnonzero(~ok)[0]) + 1  # a run never wraps past a refused turn: begin just after one
    runs, run = [], []
    for j in range(k):
        i = (start + j) % k
        if ok[i]:
            run.append(i)
        elif run:
            runs.append(run)
            run = []
    if run:
        runs.append(run)
    longest = max(len(r) for r in runs)
    pick = next(r for r in runs if len(r) == longest)
    return int(pick[(len(pick) - 1) // 2])


def part_checked(detections: list, frame: RangeImage, cloud: np.ndarray, objects, cfg, icp: bool,
                 timings: dict | None = None) -> list:
    """Copies of ``detections`` (:class:`detector.geometry.types.Detection`) of objects with a part symmetry, each
    turned about its axis to :func:`part_turn`'s choice; others unchanged.

    frame: the frame's :class:`detector.geometry.verify.RangeImage`; cloud: (M,3) camera frame, metres, the points it
    was made of; objects: the :class:`detector.geometry.types.ObjectInfo`; cfg: the
    :class:`detector.geometry.types.GeometryConfig` (depth tolerance and free-space margin as
    :func:`detector.geometry.verify.depth_checked` takes them). ``detector.infer.estimate`` checks the poses after
    ICP and the unrefined ones after ICP has started from them. With ``icp``, a turned two-stage detection (one that
    carries ``points``) is refined by ICP from there alone and rescored by its support
    (:func:`detector.geometry.icp.refine_turned`); a turn changes no score otherwise (the body, which the score sees, is the same). Adds
    "part_check" seconds."""
    t0 = time.perf_counter()
    out = list(detections)
    cloud = np.asarray(cloud, np.float64)
    for k, d in enumerate(detections):
        if d.obj_id not in objects.part_symmetries:
            continue
        dia = objects.diameters[d.obj_id]
        odd = objects.odd_points[d.obj_id]
        odd = odd[:: max(1, len(odd) // PART_POINTS)]
        tol = cfg.depth_tolerance * support_radius(cfg.support_distance, cfg.support_floor, dia)
        Rk, tk = turned_poses(d.R, d.t, objects.part_symmetries[d.obj_id])
        seen, through = depth_votes(frame, odd, Rk, tk, tol, 2 * tol)
        best = part_turn(seen, through, len(odd))
        if best == 0:
            continue
        R, t, score = Rk[best], tk[best], d.score
        if icp and d.points is not None and len(d.points):
            R, t, score = refine_turned(cloud[d.points], d.obj_id, R, t, objects, cfg)
        out[k] = replace(d, R=R, t=t, score=score)
    if timings is not None:
        timings["part_check"] = timings.get("part_check", 0.0) + time.perf_counter() - t0
    return out
