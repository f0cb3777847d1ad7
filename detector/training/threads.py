"""Torch thread counts of the two-stage training on a CPU, where the stages train side by side.

Stage 1 does not gain from a second torch thread on a 2-core machine (0.28 s a step with one or two; its steps are
many small ops), and stage 2 gains 1.3-1.4x. So :func:`detector.two_stage.train_two_stage` trains them at the same time,
stage 2 in a process of its own: stage 1 on half the threads, stage 2 on the rest until stage 1 ends, then on all
(BENCHMARKS.md). A step's result depends on how many threads computed it (their shares of a sum round differently),
so the thread counts follow the step, never the clock: stage 2's first ``narrow_steps`` steps take the narrow count
and the later ones the wide count, and at its first wide step stage 2 waits for stage 1 to end. A run therefore
gives the same weights side by side, one stage after the other or resumed, on machines with the same thread count.
``narrow_steps`` 0 trains the stages one after the other, each on all threads: the runs saved before this module
(``checkpoints/ycbv3.pt``'s among them) trained that way.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import torch

from detector.errors import DetectorError

#: Stage-2 steps per stage-1 step while they train side by side on two cores (the default stage 1 at 0.40 s a step
#: and the default stage 2 at 0.24, machine C, 2026-12-06): ``narrow_steps`` is this times stage 1's steps, so that
#: neither stage waits long for the other.
STAGE2_STEPS_PER_STAGE1_STEP = 1.7


def split_threads(total: int) -> tuple[int, int]:
    """(stage 1's threads, stage 2's narrow threads) of ``total`` torch threads: half each (at least one each)."""
    first = max(1, total // 2)
    return first, max(1, total - first)


def default_narrow_steps(stage1_steps: int) -> int:
    """Stage 2's narrow steps when the run does not set them: about as many as it takes while stage 1 trains."""
    return int(round(STAGE2_STEPS_PER_STAGE1_STEP * stage1_steps))


def check_parent(parent: int | None) -> None:
    """Raise a DetectorError when this process's parent is no longer ``parent`` (None: no check): a stage 2 whose
    ``detector train`` process has ended (killed) stops instead of training on alone."""
    if parent is not None and os.getppid() != parent:
        raise DetectorError("stage 2 stopped: the detector train process that started it has ended")


@dataclass
class ThreadPlan:
    """Stage 2's torch threads by step: ``narrow`` before step ``narrow_steps`` (0-based), ``wide`` from there.

    wait: called once before the first wide step, returns when stage 1 has ended (None: stage 1 is not running);
    parent: the process id that must stay stage 2's parent (side by side: the ``detector train`` process; None: no
    check). An orphaned stage 2 stops at its next step instead of training on alone.
    """

    narrow_steps: int
    narrow: int
    wide: int
    wait: Callable[[], None] | None = None
    parent: int | None = None

    def threads(self, step: int) -> int:
        """The torch threads of 0-based step ``step``."""
        return self.narrow if step < self.narrow_steps else self.wide

    def before_step(self, step: int) -> None:
        """Set torch's threads for 0-based step ``step``, waiting for stage 1 before the first wide one."""
        check_parent(self.parent)
        if step >= self.narrow_steps and self.wait is not None:
            self.wait()
            self.wait = None
        want = self.threads(step)
        if want != torch.get_num_threads():
            torch.set_num_threads(want)
