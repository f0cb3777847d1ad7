"""Join the shards of a capture (``argen capture-sim --shard I/N`` on N machines) into one dataset.

Shard ``I`` of ``N`` made the frames whose index is ``I`` modulo ``N``, each from the same per-frame
generator a single run would use, so the merged folder equals a single-machine run with the same seed
and options (images byte for byte, JSON files key for key; only the timings in capture_log.json differ).
The merge is built in ``OUT.partial/`` and renamed onto ``OUT`` at the end: an interrupted merge leaves
no half dataset, and running it again starts over (images are hard links where the file system allows,
so a merge costs little).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from argen import bop
from argen.errors import ArgenError
from argen.fileio import read_json, write_json


@dataclass
class Shard:
    """One shard folder: its argen.json, its capture log entries (by frame index) and its (I, N)."""

    root: Path
    meta: dict
    log: dict[int, dict]
    index: int
    count: int


def read_shard(root: Path) -> Shard:
    """Read a shard folder's argen.json and capture_log.json; ArgenError when it is not a capture."""
    root = Path(root)
    if not root.is_dir():
        raise ArgenError(f"shard folder not found: {root}")
    meta = read_json(root / "argen.json", "argen.json")
    if not isinstance(meta, dict) or meta.get("kind") != "capture-sim":
        raise ArgenError(f"{root} is not a capture-sim dataset (argen.json kind is {meta.get('kind')!r})")
    log_p = root / "capture_log.json"
    if not log_p.is_file():
        raise ArgenError(f"shard {root} has no capture_log.json: it has not finished a frame; run it again")
    log = {int(e["index"]): e for e in read_json(log_p, "capture_log.json").get("frames", [])}
    i, n = meta.get("shard", [0, 1])
    return Shard(root, meta, log, int(i), int(n))


def check_shards(shards: list[Shard]) -> None:
    """All shards of one capture, each complete, none missing or repeated; ArgenError naming the problem."""
    first = shards[0]
    same = ("config", "models", "objects", "frames", "template", "seed", "split")
    for s in shards[1:]:
        for key in same:
            if s.meta.get(key) != first.meta.get(key):
                raise ArgenError(f"{s.root} and {first.root} differ in '{key}': they are not shards of one capture")
    n = first.count
    if any(s.count != n for s in shards):
        raise ArgenError("the shards were made with different --shard counts N")
    seen = sorted(s.index for s in shards)
    if seen != list(range(n)):
        missing = sorted(set(range(n)) - set(seen))
        repeated = sorted({i for i in seen if seen.count(i) > 1})
        what = (f"missing shard(s) {', '.join(f'{i}/{n}' for i in missing)}" if missing
                else f"shard(s) {', '.join(f'{i}/{n}' for i in repeated)} given twice")
        raise ArgenError(f"cannot merge: {what}")
    frames = int(first.meta["frames"])
    for s in shards:
        want = set(range(s.index, frames, n))
        if set(s.log) != want:
            raise ArgenError(f"shard {s.index}/{n} ({s.root}) is incomplete: {len(set(s.log) & want)} of "
                             f"{len(want)} frames; run its command again to finish it")


def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def merge_captures(shard_dirs: list[Path], out: Path, overwrite: bool = False) -> int:
    """Merge capture shards into ``out``; returns the number of accepted frames. ArgenError on any mismatch."""
    if not shard_dirs:
        raise ArgenError("give the shard folders to merge")
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise ArgenError(f"output folder {out} is not empty; use --overwrite or choose another --out")
    shards = [read_shard(Path(d)) for d in shard_dirs]
    check_shards(shards)
    split = shards[0].meta["split"]
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    shutil.copytree(shards[0].root / "models", tmp / "models")
    if (shards[0].root / "models_eval").is_dir():
        shutil.copytree(shards[0].root / "models_eval", tmp / "models_eval")
    shutil.copyfile(shards[0].root / bop.CAMERA_FILE, tmp / bop.CAMERA_FILE)
    jsons = bop.SceneJsons(tmp, split)
    for s in shards:
        split_dir = s.root / split
        for scene_dir in sorted(p for p in split_dir.iterdir() if p.is_dir()) if split_dir.is_dir() else []:
            sid = int(scene_dir.name)
            merged = jsons.scene(sid)
            parts = bop.load_scene_jsons(s.root, split, sid)
            for name in bop.SCENE_FILES:
                part = parts[name]
                clash = set(part) & set(merged[name])
                if clash:
                    raise ArgenError(f"scene {sid} image {sorted(clash, key=int)[0]} appears in two shards")
                merged[name].update(part)
            jsons.touch(sid)
            for f in scene_dir.rglob("*"):
                if f.is_file() and f.suffix != ".json" and not f.name.startswith(".tmp-"):
                    _link_or_copy(f, tmp / split / scene_dir.name / f.relative_to(scene_dir))
    jsons.flush()
    bop.save_test_targets(tmp, split)
    log = {}
    for s in shards:
        log.update(s.log)
    write_json(tmp / "capture_log.json", {"frames": [log[k] for k in sorted(log)]}, indent=1)
    meta = {k: v for k, v in shards[0].meta.items() if k != "shard"}
    write_json(tmp / "argen.json", meta)
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return sum(1 for e in log.values() if e.get("accepted"))
