"""Offline training of W: featurize scans, standardise, solve Eq. 3, write a model."""

from vbrl_ros.training.fit import TrainingResult, fit_model, one_hot, standardization

__all__ = ["TrainingResult", "fit_model", "one_hot", "standardization"]
