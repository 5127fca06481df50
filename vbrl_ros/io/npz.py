"""Reading data-only ``.npz`` files (models, keyframe databases) with one-line errors.

Always ``allow_pickle=False``: these files are data, never code. Every way a
file can be unreadable — missing, truncated, not a zip, pickled object
arrays — becomes one exception of the caller's type with a one-line message
a node can log.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np


def one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def read_npz(path: str | Path, error_type: type[Exception], what: str) -> dict[str, np.ndarray]:
    """All arrays of ``path``; problems raise ``error_type`` naming ``what`` (e.g. "model")."""
    path = Path(path)
    if not path.is_file():
        raise error_type(f"{what} file {path} does not exist")
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as error:
        raise error_type(
            f"{path} is not a readable .npz {what} (truncated or corrupt, or pickled?): "
            f"{one_line(error)}"
        ) from None
