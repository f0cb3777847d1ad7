"""Loading a checkpoint for inference (:class:`Checkpoint`: one network, or both stages of a two-stage model) and
writing the two-stage model file. The file format, and the renaming of older key names on load, is
:mod:`detector.training.checkpoint_file`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from argen.h5 import LabelFile
from detector.data.augment import reads_colour
from detector.data.frames import object_table_dict
from detector.errors import DetectorError, argen_errors
from detector.geometry.types import same_mesh
from detector.stage1.network import ModelConfig, PointNet2
from detector.stage1.sampling import SamplingConfig
from detector.stage2.colour_level import colour_levels
from detector.stage2.network import build_stage2_net
from detector.training.checkpoint_file import FORMAT, TWO_STAGE_VERSION, atomic_torch_save, read_checkpoint


@dataclass
class Checkpoint:
    """A trained network ready for inference, and what it was trained on.

    model: PointNet2 in eval mode on the requested device; class_ids: object id of class index c + 1;
    objects: the label file's object table as plain lists (ids, names, diameters metres, symmetric,
    control_points (M, 9, 3) metres, model_points (M, P, 3) metres, sym_transforms per object (S, 4, 4), and,
    where the label file had them, shape_symmetries, texture_points and texture_colours per object, and
    part_symmetries and odd_points, those of a two-stage model from stage 2's label file);
    num_points: points sampled per frame; step: training steps done; extra: train config, metrics;
    normalisation: the network input's colour normalisation (``detector.data.augment.input_normalisation``: with
    "colour": "none" the network has no colour input);
    stage2_net: a two-stage model's crop network (stage 2) or None; stage2: its part of the file (configs, classes,
    ``colour_levels``: each class's colour level in its training file or None, ``infer.colour_level``) without the
    weights; geometry_config: inference settings stored with the model ({} for none); plane_keep: the
    share of a frame's dominant plane that the network's sampling keeps, as it was trained (1 for models trained
    before that setting); num_points and ``model_config.npoints[0]`` (the keypoints the network predicts at) are
    the inference's, which a model file's sampling settings (:class:`SamplingConfig`) may set above the training's;
    sampling: those settings (:class:`detector.stage1.sampling.SamplingConfig`'s values), as applied.
    """

    model: Any
    model_config: Any
    class_ids: list[int]
    objects: dict
    num_points: int
    step: int
    extra: dict
    normalisation: dict = field(default_factory=dict)
    stage2_net: Any = None
    stage2: dict | None = None
    geometry_config: dict = field(default_factory=dict)
    plane_keep: float = 1.0
    sampling: dict = field(default_factory=dict)

    @property
    def sampling_used(self) -> dict:
        """How stage 1 samples a frame, for reports: the sampling settings plus the points drawn and the keypoints
        predicted at in each pass, e.g. ``{"density": 1.0, "passes": 1, "points": 4096, "keypoints": 1024}``."""
        return {**self.sampling, "points": self.num_points, "keypoints": self.model_config.npoints[0]}


def build_model(payload: dict, path: Path, device: str | torch.device):
    """The PointNet2 of a checkpoint dict with its weights loaded; a mismatch is a :class:`DetectorError`."""

    try:
        cfg = ModelConfig.from_dict(payload["model_config"])
        model = PointNet2(cfg, num_classes=len(payload["class_ids"]))
        model.load_state_dict(payload["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DetectorError(f"{path}: the weights do not match the stored model config ({first})") from None
    return model.to(device), cfg


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu", sampling: dict | None = None) -> Checkpoint:
    """Load a checkpoint for inference: the model (both stages of a two-stage one) in eval mode on ``device``
    plus its metadata. Stage 1 samples as the model file's sampling settings say (:class:`SamplingConfig`; a model
    file without them samples as it trained), with ``sampling`` (e.g. ``{"density": 1}``, from ``--set``) over
    them."""
    path = Path(path)
    payload = read_checkpoint(path, "cpu")
    stage2_net, stage2 = None, None
    if payload["version"] == TWO_STAGE_VERSION:
        if "stage1" not in payload:
            raise DetectorError(f"{path} holds a stage-2 network only; use the two-stage model file (model.pt) "
                                "that `detector train` writes")
        stage2 = {k: v for k, v in payload["stage2"].items() if k not in ("model_state", "train_state")}
        stage2_net = build_stage2_net(payload["stage2"], str(path), device).eval()
        extra_top = payload.get("extra") or {}
        payload = payload["stage1"]
    else:
        extra_top = {}
    chosen = SamplingConfig.from_dict({**(extra_top.get("sampling_config") or {}), **(sampling or {})})
    num_points = chosen.scaled(int(payload["num_points"]))
    if chosen.density != 1:
        stored = payload["model_config"]
        npoints = list(stored.get("npoints") or [])
        if not npoints:
            raise DetectorError(f"{path}: the model config lacks its sampling levels (npoints)")
        keypoints = chosen.scaled(npoints[0])  # at most num_points: training has npoints[0] <= num_points
        if len(npoints) > 1 and keypoints < npoints[1]:
            raise DetectorError(f"sampling.density {chosen.density} leaves {keypoints} keypoints, under the "
                                f"network's next level's {npoints[1]}")
        payload = {**payload, "model_config": {**stored, "npoints": [keypoints, *npoints[1:]]}}
    model, cfg = build_model(payload, path, device)
    model.eval()
    objects = payload["objects"]
    if stage2 is not None and (stage2.get("objects") or {}).get("part_symmetries"):
        # the part symmetries stage 2 was taught under are those of its label file (stage 1 may have had another)
        objects = {**objects, **{k: stage2["objects"][k] for k in ("part_symmetries", "odd_points")}}
    return Checkpoint(model=model, model_config=cfg, class_ids=list(payload["class_ids"]),
                      objects=objects, num_points=num_points, step=int(payload["step"]),
                      extra=payload.get("extra") or {}, normalisation=payload.get("normalisation") or {},
                      stage2_net=stage2_net, stage2=stage2,
                      geometry_config=dict(extra_top.get("geometry_config") or {}),
                      plane_keep=trained_plane_keep(payload), sampling=vars(chosen))


def trained_plane_keep(payload: dict) -> float:
    """The share of a frame's dominant plane that a network's sampling kept in training (its ``plane_keep``
    setting, :mod:`detector.data.plane`), from its checkpoint dict (a stage-1 or single-network payload); 1 for
    networks trained before that setting."""
    return float(((payload.get("extra") or {}).get("train_config") or {}).get("plane_keep", 1.0))


def save_two_stage(path: str | Path, stage1: dict, stage2: dict, extra: dict | None = None) -> Path:
    """Write a two-stage model file (version 3) from a stage-1 checkpoint dict and a stage-2 part, without their
    training states (what inference needs only). extra: e.g. {"geometry_config": {...}, "sampling_config":
    {"density": 1.25}, "timing": ...}."""
    d = {k: v for k, v in stage1.items() if k not in ("format", "version", "train_state")}
    p = {k: v for k, v in stage2.items() if k != "train_state"}
    path = Path(path)
    atomic_torch_save({"format": FORMAT, "version": TWO_STAGE_VERSION, "stage1": d, "stage2": p, "extra": extra or {}},
                      path)
    return path


def label_rows(objects: dict, ids, table: dict, path, label_path) -> list[int]:
    """The row of each of ``ids`` in a label file's object ``table`` (:func:`object_table_dict`), each checked to be
    the model's object: ``objects`` is the model file's object table (its ``ids`` and ``diameters``, metres), the same
    mesh has the same diameter. path / label_path name the two files in the one-line DetectorError of an object the
    label file lacks or holds with another mesh."""
    where = {int(i): k for k, i in enumerate(table["ids"])}
    model = {int(i): float(d) for i, d in zip(objects["ids"], objects["diameters"])}
    rows = []
    for i in ids:
        k = where.get(int(i))
        if k is None:
            raise DetectorError(f"object {i} of {path} is not in {label_path}")
        if not same_mesh(model[int(i)], table["diameters"][k]):
            raise DetectorError(f"object {i}'s diameter is {float(table['diameters'][k]):.4f} m in {label_path} and "
                                f"{model[int(i)]:.4f} m in {path}: not the same mesh")
        rows.append(k)
    return rows


def add_surfaces(path: str | Path, label_path: str | Path, out: str | Path | None = None) -> Path:
    """Write a model file whose object table also carries the label file's surface samples and their normals
    (``surface_points`` (S,3) metres and ``surface_normals`` (S,3) unit, per object: what the surface-continuation
    check needs, :func:`detector.geometry.verify.continuation_checked`), for a model trained on a label file written
    before they existed. The weights and every other field stay as they were (a version-2 file is written with
    version 3's key names, as :func:`read_checkpoint` reads it); the label file must carry the normals
    and every one of the model's objects, with the same diameters (the same meshes). out: the file written
    (atomically; None: ``path`` itself). A label file of the same meshes written with ``argen label``'s default seed
    carries the same samples as the model's training file would have."""
    payload = read_checkpoint(path)
    if payload.get("version") == TWO_STAGE_VERSION and "stage1" not in payload:
        raise DetectorError(f"{path} holds a stage-2 network only; use the two-stage model file (model.pt) "
                            "that `detector train` writes")
    part = payload["stage1"] if "stage1" in payload else payload
    objects = part.get("objects")
    if not isinstance(objects, dict) or "ids" not in objects:
        raise DetectorError(f"{path} carries no object table")
    with argen_errors():
        with LabelFile(label_path) as lf:
            table = object_table_dict(lf.objects)
    rows = label_rows(objects, objects["ids"], table, path, label_path)
    points, normals = [], []
    for i, k in zip(objects["ids"], rows):
        if k >= len(table["surface_points"]) or not len(table["surface_points"][k]):
            raise DetectorError(f"{label_path} carries no surface normals of object {i} (label files written before "
                                "2026-12-07 lack them: run argen label again)")
        points.append(table["surface_points"][k])
        normals.append(table["surface_normals"][k])
    part["objects"] = {**objects, "surface_points": points, "surface_normals": normals}
    target = Path(out) if out is not None else Path(path)
    atomic_torch_save(payload, target)
    return target


def add_colour_levels(path: str | Path, label_path: str | Path, out: str | Path | None = None,
                      enable: bool = True) -> Path:
    """Write a two-stage model file whose stage 2 also carries each object's colour level in a label file of its
    training data (:func:`detector.stage2.colour_level.colour_levels`: what ``infer.colour_level`` needs), for a model
    trained before ``detector train`` stored them; with ``enable`` its stored inference settings turn
    ``colour_level`` on. The weights and every other field stay as they were. label_path: a capture of the same
    objects (the same diameters: the same meshes) made as the stage-2 training file was (the level is the renderer's,
    so the training file itself or another capture of its recipe). out: the file written (atomically; None:
    ``path`` itself)."""
    payload = read_checkpoint(path)
    if payload.get("version") != TWO_STAGE_VERSION or "stage1" not in payload or "stage2" not in payload:
        raise DetectorError(f"{path} is not a two-stage model file (model.pt that `detector train` writes)")
    part = payload["stage2"]
    if not reads_colour(part.get("normalisation")):
        raise DetectorError(f"{path}'s stage 2 reads no colour: it has no colour level to keep")
    with argen_errors():
        with LabelFile(label_path) as lf:
            table = object_table_dict(lf.objects)
    ids = [int(i) for i in part["class_ids"]]
    label_rows(payload["stage1"]["objects"], ids, table, path, label_path)
    with argen_errors():
        levels = colour_levels(label_path, ids)
    if all(v is None for v in levels):
        raise DetectorError(f"{label_path} holds no instance of the model's objects with enough labelled points")
    part["colour_levels"] = levels
    if enable:
        part["infer_config"] = {**(part.get("infer_config") or {}), "colour_level": True}
    target = Path(out) if out is not None else Path(path)
    atomic_torch_save(payload, target)
    return target


def combine_stages(stage1_model: str | Path, stage2_model: str | Path, out: str | Path,
                   settings_from: str = "stage2") -> Path:
    """Write a two-stage model file with the stage 1 of one model file and the stage 2 of another (e.g. to measure
    what each stage of a recipe does, RESULTS.md). Both must be two-stage model files of the same objects, in the
    same class order, with the same diameters (the same meshes). The inference settings (``geometry``,
    ``sampling``; stage 2's own ``infer``) are taken from ``settings_from``'s file ("stage1" or "stage2");
    stage 1's object table goes with stage 1, as in every model file. out: the file written (atomically)."""
    if settings_from not in ("stage1", "stage2"):
        raise DetectorError(f"settings_from must be stage1 or stage2, got {settings_from!r}")
    parts = []
    for path in (stage1_model, stage2_model):
        payload = read_checkpoint(path)
        if payload.get("version") != TWO_STAGE_VERSION or "stage1" not in payload or "stage2" not in payload:
            raise DetectorError(f"{path} is not a two-stage model file (model.pt that `detector train` writes)")
        parts.append(payload)
    first, second = parts
    ids1, ids2 = list(first["stage1"]["class_ids"]), list(second["stage2"]["class_ids"])
    if ids1 != ids2:
        raise DetectorError(f"{stage1_model}'s stage 1 learned objects {ids1}, {stage2_model}'s stage 2 {ids2}")
    table1, table2 = first["stage1"]["objects"], second["stage1"]["objects"]
    for i, a, b in zip(table1["ids"], table1["diameters"], table2["diameters"]):
        if not same_mesh(a, b):
            raise DetectorError(f"object {i}'s diameter is {float(a):.4f} m in {stage1_model} and {float(b):.4f} m "
                                f"in {stage2_model}: not the same mesh")
    extra = (first if settings_from == "stage1" else second).get("extra") or {}
    stage2 = dict(second["stage2"])
    if settings_from == "stage1":
        stage2["infer_config"] = first["stage2"].get("infer_config", stage2.get("infer_config"))
    return save_two_stage(out, first["stage1"], stage2, extra)
