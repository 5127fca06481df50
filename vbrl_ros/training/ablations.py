"""The paper's three ablations of the full VBRL objective, and where their model files live.

Each ablation switches off part of the structured-sparsity regulariser of Eq. 3,
relative to the full model's (λ1, λ2):

=================  ==========  ==========================================================
name               (λ1, λ2)    what is left
=================  ==========  ==========================================================
``concatenation``  (0, 0)      plain least squares on the concatenated descriptor
``voxel-only``     (λ1, 0)     only the voxel group norm
``modality-only``  (0, λ2)     only the modality group + row norms
=================  ==========  ==========================================================

They are written next to the full model as siblings ``MODEL.<name>.npz`` (for
``runs/town.npz``: ``runs/town.concatenation.npz`` ...), so ``vbrl eval --model
runs/town.npz`` finds them without extra arguments.
"""

from __future__ import annotations

from pathlib import Path

#: Ablation name -> (use λ1?, use λ2?) of the full model.
ABLATIONS: dict[str, tuple[bool, bool]] = {
    "concatenation": (False, False),
    "voxel-only": (True, False),
    "modality-only": (False, True),
}

#: Label of the full model in tables and plots.
FULL_NAME = "VBRL"


def ablation_lambdas(name: str, lambda1: float, lambda2: float) -> tuple[float, float]:
    """(λ1, λ2) of ablation ``name`` given the full model's pair."""
    if name not in ABLATIONS:
        raise ValueError(f"unknown ablation {name!r}; known: {', '.join(ABLATIONS)}")
    keep1, keep2 = ABLATIONS[name]
    return (lambda1 if keep1 else 0.0, lambda2 if keep2 else 0.0)


def model_stem(model_path: str | Path) -> Path:
    """``runs/town.npz`` -> ``runs/town``: the prefix every sibling file shares."""
    path = Path(model_path)
    return path.with_suffix("") if path.suffix == ".npz" else path


def sibling_path(model_path: str | Path, suffix: str) -> Path:
    """``runs/town.npz`` + ``"voxel-only.npz"`` -> ``runs/town.voxel-only.npz``.

    Also used for the figures (``"modalities.png"`` -> ``runs/town.modalities.png``).
    """
    stem = model_stem(model_path)
    return stem.with_name(f"{stem.name}.{suffix}")


def ablation_path(model_path: str | Path, name: str) -> Path:
    if name not in ABLATIONS:
        raise ValueError(f"unknown ablation {name!r}; known: {', '.join(ABLATIONS)}")
    return sibling_path(model_path, f"{name}.npz")


def discover_ablations(model_path: str | Path) -> tuple[dict[str, Path], list[str]]:
    """Ablation files present next to ``model_path`` (name -> path), and the missing names."""
    found, missing = {}, []
    for name in ABLATIONS:
        path = ablation_path(model_path, name)
        if path.is_file():
            found[name] = path
        else:
            missing.append(name)
    return found, missing
