"""Stage-2 (crop network) training step on a CPU: the data work of a batch and the network step, each as the
current code does it and as it was done before (issue 17).

Usage: .venv/bin/python bench/bench_train_pose.py --data data/lm_train.h5 [--batches 20] [--rounds 3] [--threads 2]
                                                  [--bfloat16]

Data: the median time to make one batch (``batch_frames`` frames' crops with the default augmentation) in this
process, reading every frame from the label file ("read") or cutting it from the frames' cached crop regions
("cached", ``Stage2TrainConfig.cache_mb``; a first pass fills the cache, untimed). Network: the median of forward +
loss + backward + AdamW over the same prepared batches, with the edge-convolutions' training max as
``detector.stage2.network._NeighbourMax`` ("running max") or as the earlier gather to (B, n, k, C) and max ("gather").
With ``--bfloat16`` also the running max with the forward and loss in bfloat16 (``stage2.net_dtype``, torch's CPU
autocast). The rounds alternate the forms so that a VM's drift hits them all; medians over all rounds. In a training run the
data work runs in a loader process beside the network step on the same cores, so both add to a step's time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from detector.stage2 import network as cropnet
from detector.stage2.dataset import CropDataset, collate_crops
from detector.stage2.train import forward_stage2_loss, load_stage2_config


def gather_max(b: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """The earlier training path's neighbour max: (R, C) rows, (M, k) indices -> (M, C) via a ``torch.gather`` to
    (M, k, C) and a max over k, as ``EdgeConv`` did before ``_NeighbourMax``."""
    M, k = rows.shape
    nb = torch.gather(b[None], 1, rows.reshape(1, M * k, 1).expand(-1, -1, b.shape[1]))
    return nb.reshape(M, k, -1).max(dim=1).values


def network_step_times(batches: list, cfg, seed: int = 0) -> list[float]:
    """Seconds of forward + loss + backward + AdamW for each batch (a fresh seeded network; the forward and loss in
    ``cfg.net_dtype``)."""
    torch.manual_seed(seed)
    net = cropnet.CropNet(cfg.net, 8)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    out = []
    for batch in batches:
        t = time.perf_counter()
        loss, _ = forward_stage2_loss(net, batch, cfg, torch.device("cpu"))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        out.append(time.perf_counter() - t)
    return out[1:]  # the first step warms up


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a label file (the training set)")
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--bfloat16", action="store_true", help="also time the running max in bfloat16")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = load_stage2_config(None, {"crop.neighbour": 0.5})
    nf = cfg.batch_frames
    read = CropDataset(a.data, cfg.crop, augment=True, seed=0)
    cached = CropDataset(a.data, cfg.crop, augment=True, seed=0, cache_mb=cfg.cache_mb)
    keys = [[(1, (j * nf + i) % len(read)) for i in range(nf)] for j in range(a.batches)]
    for ks in keys:  # fill the cache (the first epoch of a run)
        for k in ks:
            cached[(0, k[1])]
    times: dict[str, list[float]] = {"data read": [], "data cached": [], "network gather": [],
                                     "network running max": []}
    apply = cropnet._NeighbourMax.apply
    forms = [("network gather", gather_max, cfg), ("network running max", apply, cfg)]
    if a.bfloat16:
        forms.append(("network running max, bfloat16", apply,
                      load_stage2_config(None, {"crop.neighbour": 0.5, "net_dtype": "bfloat16"})))
        times["network running max, bfloat16"] = []
    batches = None
    for r in range(a.rounds):
        for name, ds in (("data read", read), ("data cached", cached)):
            made = []
            for ks in keys:
                t = time.perf_counter()
                made.append(collate_crops([ds[k] for k in ks]))
                times[name].append(time.perf_counter() - t)
            batches = made
        for name, fn, c in (forms if r % 2 == 0 else forms[::-1]):
            cropnet._NeighbourMax.apply = fn
            times[name] += network_step_times(batches, c)
        cropnet._NeighbourMax.apply = apply
    crops = statistics.mean(len(b["cls"]) for b in batches)
    res = {k: round(statistics.median(v), 4) for k, v in times.items()}
    res.update({"crops_per_batch": round(crops, 1), "threads": a.threads, "batches": a.batches, "rounds": a.rounds,
                "cached_mb_per_frame": round(cached._cached / max(len(cached._cache), 1) / 2 ** 20, 3)})
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
