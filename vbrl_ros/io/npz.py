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
    """All arrays of ``path``; problems raise ``error_type`` naming ``what`` (e.g. "model").

    A file that is no ``.npz`` at all (text, a lone ``.npy``, random bytes, a
    plain zip) is told apart before numpy sees it: numpy would report a text
    file as "pickled data", which sends a user looking for the wrong problem.
    """
    path = Path(path)
    if not path.is_file():
        raise error_type(f"{what} file {path} does not exist")

    def refuse(reason: str) -> Exception:
        return error_type(f"{path} is not a vbrl_ros {what} file ({reason})")

    with open(path, "rb") as handle:
        head = handle.read(512)
    if not head.startswith(ZIP_MAGIC):
        raise refuse(_not_a_zip(head))
    try:
        with np.load(path, allow_pickle=False) as archive:
            foreign = [name for name in archive.zip.namelist() if not name.endswith(".npy")]
            if foreign:
                raise refuse(f"a zip archive, not an .npz: {foreign[0]!r} is not a .npy array")
            return {key: archive[key] for key in archive.files}
    except ValueError as error:
        if isinstance(error, error_type):
            raise
        if "pickle" in str(error).lower():
            raise refuse("it holds pickled object arrays, which are never loaded: "
                         "allow_pickle=False") from None
        raise refuse(f"an unreadable .npz archive: {one_line(error)}") from None
    except (zipfile.BadZipFile, EOFError, OSError, KeyError) as error:
        raise refuse(f"a truncated or corrupt .npz archive: {one_line(error)}") from None


#: How every zip file, and so every ``.npz``, begins (a local file header, or an empty archive).
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def _not_a_zip(head: bytes) -> str:
    """What a file that does not start like a zip archive looks like, in a few words."""
    if not head:
        return "it is empty"
    if head.startswith(b"\x93NUMPY"):
        return "it is a single .npy array, not an .npz archive"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as error:
        # a multi-byte character cut at the end of the sample is still text
        text = head[:error.start].decode("utf-8") if error.start >= len(head) - 3 else None
    if text is not None and "\x00" not in text and all(c.isprintable() or c in "\t\r\n\f" for c in text):
        return "it is a text file, not an .npz archive"
    return "not an .npz archive"


def foreign_format(contents: dict[str, np.ndarray], expected: str) -> str:
    """Why an ``.npz`` without the ``format`` tag ``expected`` is another file, in a few words."""
    tag = contents.get("format")
    if tag is not None and tag.ndim == 0 and tag.dtype.kind == "U":
        return f"its format tag is '{tag}', not '{expected}'"
    names = sorted(contents)
    listed = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
    return f"an .npz without the format tag '{expected}'; it holds {listed or 'no arrays'}"
