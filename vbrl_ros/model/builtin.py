"""The built-in default model, shipped with the package so ``vbrl_node`` works out of the box.

Only loading lives here; :mod:`vbrl_ros.training.builtin_model` builds the
file (``vbrl demo --rebuild-default-model``).
"""

from __future__ import annotations

from pathlib import Path

from vbrl_ros.model.model_file import ModelFileError, VBRLModel, load_model

DEFAULT_MODEL_PATH = Path(__file__).resolve().parents[1] / "data" / "default_model.npz"


def load_default_model() -> VBRLModel:
    if not DEFAULT_MODEL_PATH.is_file():
        raise ModelFileError(
            f"the built-in default model {DEFAULT_MODEL_PATH} is missing; "
            "rebuild it with `vbrl demo --rebuild-default-model` or set model_path"
        )
    return load_model(DEFAULT_MODEL_PATH)
