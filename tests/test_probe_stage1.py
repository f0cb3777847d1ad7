"""bench/probe_stage1.py's rule for which object stage 1 takes an instance for: the most common object label among
its sampled points, background left out, its own object where that ties, 0 where no point is labelled an object."""

from __future__ import annotations

import numpy as np


def test_taken_object_is_the_most_common_object_label_and_ignores_background(repo_script):
    taken = repo_script("bench/probe_stage1.py").taken_object
    # an eggbox (10) whose points are mostly background, then can (5) more often than eggbox
    assert taken(np.array([0, 0, 0, 0, 5, 5, 10]), 10) == 5
    assert taken(np.array([0, 0, 0, 10, 10, 5]), 10) == 10
    assert taken(np.array([0, 0, 0]), 10) == 0
    assert taken(np.array([12, 12, 12, 1]), 1) == 12  # a label above the instance's own id


def test_taken_object_ties_go_to_the_own_object_whatever_the_ids(repo_script):
    taken = repo_script("bench/probe_stage1.py").taken_object
    assert taken(np.array([5, 10]), 10) == 10  # the lower id does not win a tie against the own object
    assert taken(np.array([5, 10, 0, 0]), 5) == 5
    assert taken(np.array([5, 5, 10, 10, 6]), 6) in (5, 10)  # a tie between two others: one of them, not the own
