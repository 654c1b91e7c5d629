"""The integrated ANN-EKF (Horvath & Neuner 2024): EKFTrainer, its configuration and result; the adaptive filter."""

from torchcal.filter._kalman import FlatModule
from torchcal.filter.adaptive import AdaptiveConfig, AdaptiveEKF, AdaptiveResult, random_features
from torchcal.filter.ekf import EKFConfig, EKFResult, EKFTrainer

__all__ = [
    "AdaptiveConfig",
    "AdaptiveEKF",
    "AdaptiveResult",
    "EKFConfig",
    "EKFResult",
    "EKFTrainer",
    "FlatModule",
    "random_features",
]
