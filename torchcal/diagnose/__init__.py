"""Residual diagnosis: candidate effects -> score tests -> joint refit -> validation (the closed loop)."""

from torchcal.diagnose.candidates import Candidate, candidates
from torchcal.diagnose.loop import Decision, Diagnosis, close_loop
from torchcal.diagnose.score import Score, score_candidates

__all__ = ["Candidate", "Decision", "Diagnosis", "Score", "candidates", "close_loop", "score_candidates"]
