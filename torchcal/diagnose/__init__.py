"""Residual diagnosis: candidate effects and their score tests (the closed loop is :mod:`torchcal.pipeline.loop`)."""

from torchcal.diagnose.candidates import Candidate, candidates
from torchcal.diagnose.score import Score, named_p, score_candidates

__all__ = ["Candidate", "Score", "candidates", "named_p", "score_candidates"]
