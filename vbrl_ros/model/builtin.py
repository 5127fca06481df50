"""The models shipped with the package, so ``vbrl_node`` works out of the box.

``default_model.npz``: the built-in model the node and ``vbrl eval`` use (the recognition
descriptor, :mod:`vbrl_ros.training.presets`). ``paper_model.npz``: the paper's
configuration (Cartesian grid, five modalities, scenario targets) trained on simulated
scenarios, for comparison and as the benchmarks' d = 7872 descriptor.
Only loading lives here; :mod:`vbrl_ros.training.builtin_model` builds the default
file (``vbrl demo --rebuild-default-model``).
"""

from __future__ import annotations

from pathlib import Path

from vbrl_ros.model.model_file import ModelFileError, VBRLModel, load_model

DEFAULT_MODEL_PATH = Path(__file__).resolve().parents[1] / "data" / "default_model.npz"
PAPER_MODEL_PATH = DEFAULT_MODEL_PATH.with_name("paper_model.npz")


def load_default_model() -> VBRLModel:
    if not DEFAULT_MODEL_PATH.is_file():
        raise ModelFileError(
            f"the built-in default model {DEFAULT_MODEL_PATH} is missing; "
            "rebuild it with `vbrl demo --rebuild-default-model` or set model_path"
        )
    return load_model(DEFAULT_MODEL_PATH)


def load_paper_model() -> VBRLModel:
    if not PAPER_MODEL_PATH.is_file():
        raise ModelFileError(f"the shipped paper-configuration model {PAPER_MODEL_PATH} is missing")
    return load_model(PAPER_MODEL_PATH)
