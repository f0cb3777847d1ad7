"""Stage 1 (or the single-shot network) at inference: a frame -> per-point predictions (:class:`Predictions`: class
probabilities, control-point votes, confidence). :func:`network_predictor` runs a checkpoint's network on CPU or
GPU; :func:`oracle_predictor` returns the frame's ground-truth labels (checks the geometry alone)."""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch

from detector.net_dtype import check_net_dtype, net_autocast
from detector.stage1.dataset import inference_batch
from detector.stage1.sampling import SamplingConfig


@dataclass
class Predictions:
    """Per-point predictions for one frame (K points).

    xyz: (K,3) float metres; class_probs: (K,C+1) float, column 0 background, column c object ``class_ids[c-1]``;
    class_ids: C object ids; control_points: (K,9,3) float metres (point + offsets); confidence: (K,) in [0,1];
    timings: seconds spent, e.g. {"sampling", "network"}.
    """

    xyz: np.ndarray
    class_probs: np.ndarray
    class_ids: list[int]
    control_points: np.ndarray
    confidence: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def obj_ids(self) -> np.ndarray:
        """(K,) int64 object id of each point's most likely class, 0 = background."""
        lut = np.concatenate([[0], np.asarray(self.class_ids, np.int64)])
        return lut[np.argmax(self.class_probs, axis=1)]


Predictor = Callable[[object], Predictions]


def oracle_predictor(num_points: int | None = None, seed: int = 0) -> Predictor:
    """A predictor that returns the frame's ground truth: class = semantic label, control points = the per-point
    labels, confidence 1. num_points: sample that many rows per frame (seeded) like the network; None = all."""

    def predict(frame) -> Predictions:
        n = len(frame.features)
        rows = np.arange(n) if num_points is None or num_points >= n else \
            np.sort(np.random.default_rng([seed, frame.scene_id, frame.im_id]).choice(n, num_points, replace=False))
        ids = sorted(set(np.unique(frame.semantic).tolist()) - {0})
        cls = np.searchsorted(ids, frame.semantic[rows]) + 1
        cls[frame.semantic[rows] == 0] = 0
        probs = np.eye(len(ids) + 1, dtype=np.float32)[cls]
        return Predictions(frame.features[rows, :3].astype(np.float64), probs, ids,
                           frame.control_points[rows].astype(np.float64), np.ones(len(rows)))

    return predict


def network_predictor(checkpoint, seed: int = 0, device: str | None = None, net_dtype: str = "float32") -> Predictor:
    """A predictor running ``checkpoint.model`` (a :class:`detector.checkpoint.Checkpoint`) on one frame.

    Sampling and neighbour indices as in training (``detector.stage1.dataset.inference_batch``); times "sampling" and
    "network" (synchronised on GPU). On a GPU the neighbour indices are computed by the model (inside "network").
    The checkpoint's ``sampling`` settings (:class:`detector.stage1.sampling.SamplingConfig`, checked here; a model
    object without them samples as it trained, once): with ``passes`` P > 1 the frame is sampled P times (pass 0
    with ``seed``, as a single pass; pass k with the seed sequence (seed, k)), the samplings are drawn in two threads
    and go through the network as one batch of P, and the predictions are concatenated in pass order (P x K rows);
    ``fps`` "tree": the tree-based FPS on every sampling level. net_dtype: the network's number format, resolved
    (:func:`detector.net_dtype.resolve_net_dtype`: float32 or bfloat16).
    """
    sampling = SamplingConfig.from_dict(getattr(checkpoint, "sampling", None))
    passes, tree_fps = sampling.passes, sampling.fps == "tree"
    model = checkpoint.model
    dev = torch.device(device) if device else next(model.parameters()).device
    check_net_dtype(net_dtype, dev)  # a bad value fails here, not at the first frame
    model.to(dev).eval()
    seeds = [seed] + [[seed, k] for k in range(1, passes)]

    def predict(frame) -> Predictions:
        t0 = time.perf_counter()

        def draw(pass_seed):
            return inference_batch(frame.features, checkpoint.model_config, checkpoint.num_points, pass_seed,
                                   normalisation=checkpoint.normalisation or None, precompute=dev.type == "cpu",
                                   plane_keep=checkpoint.plane_keep, tree_fps=tree_fps)

        if passes == 1:
            batches = [draw(seeds[0])]
        else:  # the indices' FPS and k-d trees run outside the GIL: two samplings at a time
            with ThreadPoolExecutor(2) as pool:
                batches = list(pool.map(draw, seeds))
        rows = [b.pop("point_index").numpy() for b in batches]
        batch = {k: torch.cat([b[k] for b in batches]).to(dev) for k in batches[0]}
        feats = batch.pop("features")
        t1 = time.perf_counter()
        with torch.no_grad(), net_autocast(net_dtype):
            out = model(feats, batch or None)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
        t2 = time.perf_counter()
        kp = out["keypoints"].cpu().numpy()
        # metres, exactly the input points; only the predicted rows are made float64, not the whole frame
        points = np.asarray(frame.features)
        xyz = np.concatenate([points[r[k], :3] for r, k in zip(rows, kp)]).astype(np.float64)
        offsets = out["offsets"].double().cpu().numpy().reshape(len(xyz), *out["offsets"].shape[2:])
        probs = torch.softmax(out["logits"].float(), -1).cpu().numpy().reshape(len(xyz), -1)
        return Predictions(xyz, probs, list(checkpoint.class_ids), xyz[:, None, :] + offsets,
                           out["confidence"].double().cpu().numpy().reshape(len(xyz)),
                           {"sampling": t1 - t0, "network": t2 - t1})

    return predict
