"""The optimiser step both trainers take: gradients of the loss, optionally some parameters left out, gradient-norm
clipping, the AdamW step and the learning-rate schedule's step."""

from __future__ import annotations

import torch


def optimiser_step(loss: torch.Tensor, net: torch.nn.Module, opt: torch.optim.Optimizer, sched, grad_clip: float,
                   frozen: list[torch.nn.Parameter] | tuple = ()) -> None:
    """One step: clear the gradients, backpropagate ``loss``, drop the gradients of ``frozen`` (they take no AdamW
    step), clip the gradient norm of ``net``'s parameters to ``grad_clip`` (0 = no clipping), step ``opt`` and
    ``sched``."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    for p in frozen:
        p.grad = None
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(net.parameters(), grad_clip)
    opt.step()
    sched.step()
