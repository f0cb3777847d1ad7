"""Scores: ADD / ADD-S matching, and BOP19's pose errors and average recall."""
