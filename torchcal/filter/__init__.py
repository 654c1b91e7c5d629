"""The integrated ANN-EKF (Horvath & Neuner 2024): EKFTrainer, its configuration and result."""

from torchcal.filter.ekf import EKFConfig, EKFResult, EKFTrainer

__all__ = ["EKFConfig", "EKFResult", "EKFTrainer"]
