"""Reading data-only ``.npz`` files (models, keyframe databases) with one-line errors.

Never with pickle: these files are data, never code. Every way a file can be
unreadable — missing, truncated, not a zip, pickled object arrays, a member of
the wrong kind — becomes one exception of the caller's type with a one-line
message a node can log.

A format lists the members it defines (:class:`Member`: dtype kinds and number
of dimensions). Before anything is read, every defined member's npy header is
checked against its entry: the declared shape must be of the right kind and
exactly fill the entry, and all together may expand to at most
:data:`MAX_EXPANSION` times the file's size plus :data:`EXPANSION_ALLOWANCE`.
So a header that claims 10**12 elements or a small file of compressed zeros
fails in a line instead of allocating; members a format does not define are
never read.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: How every zip file, and so every ``.npz``, begins (a local file header, or an empty archive).
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
#: A file's arrays may take this many times the file's size in memory (vbrl_ros writes them
#: uncompressed, about 1x; ordinary compression of float data stays far below) ...
MAX_EXPANSION = 20
#: ... plus this much, so that small files of well-compressible arrays still load.
EXPANSION_ALLOWANCE = 64 << 20

_KIND_NAMES = {"U": "text", "iu": "integer", "fiu": "numeric", "f": "float", "i": "signed integer"}


@dataclass(frozen=True)
class Member:
    """What a format stores under one name: numpy dtype ``kinds`` (e.g. ``"f"``, ``"iu"``,
    ``"U"`` for text) with ``ndim`` dimensions."""

    kinds: str
    ndim: int

    def describe(self) -> str:
        kind = _KIND_NAMES.get(self.kinds, f"dtype kind {self.kinds!r}")
        if self.ndim == 0:
            return "a text string" if self.kinds == "U" else f"a single {kind} value"
        return f"a {self.ndim}-d {kind} array"  # "a 2-d", "a 1-d": every ndim reads with "a"


TEXT = Member("U", 0)
INTEGER = Member("iu", 0)
NUMBER = Member("fiu", 0)


def one_line(error: BaseException) -> str:
    return " ".join(str(error).split()) or type(error).__name__


def read_npz(path: str | Path, error_type: type[Exception], what: str, format_tag: str,
             members: Mapping[str, Member]) -> dict[str, np.ndarray]:
    """The defined ``members`` of ``path`` that it holds; problems raise ``error_type`` naming ``what``
    (e.g. "model") and the file.

    The file must carry the text member ``format`` equal to ``format_tag``. A file
    that is no ``.npz`` at all (text, a lone ``.npy``, random bytes, a plain zip)
    is told apart before numpy sees it: numpy would report a text file as
    "pickled data", which sends a user looking for the wrong problem.
    """
    path = Path(path)
    if not path.exists():
        raise error_type(f"{what} file {path} does not exist")
    if not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file"
        raise error_type(f"{what} file {path} is {kind}")

    def refuse(reason: str) -> Exception:
        return error_type(f"{path} is not a vbrl_ros {what} file ({reason})")

    with open(path, "rb") as handle:
        head = handle.read(512)
    if not head.startswith(ZIP_MAGIC):
        raise refuse(_not_a_zip(head))
    try:
        with zipfile.ZipFile(path) as archive:
            entries = {info.filename: info for info in archive.infolist()}
            foreign = [name for name in entries if not name.endswith(".npy")]
            if foreign:
                raise refuse(f"a zip archive, not an .npz: {foreign[0]!r} is not a .npy array")
            names = [name[: -len(".npy")] for name in entries]
            reader = _MemberReader(archive, path, error_type, what)
            tag = reader.read("format", entries.get("format.npy"), TEXT) if "format" in members else None
            if tag is None or str(tag) != format_tag:
                raise refuse(_foreign_format(None if tag is None else str(tag), names, format_tag))
            defined = {name: entries[f"{name}.npy"] for name in names if name in members}
            declared = {name: reader.declared(info, members[name]) for name, info in defined.items()}
            total, size = sum(declared.values()), path.stat().st_size
            if total > MAX_EXPANSION * size + EXPANSION_ALLOWANCE:
                raise error_type(
                    f"{path} declares {_size(total)} of arrays in a {_size(size)} file (more than "
                    f"{MAX_EXPANSION} times its size): refused unread, as a compressed bomb would be")
            return {name: reader.read(name, info, members[name]) for name, info in defined.items()}
    except error_type:
        raise
    except ValueError as error:
        raise refuse(f"an unreadable .npz archive: {one_line(error)}") from None
    except (zipfile.BadZipFile, EOFError, OSError, KeyError, NotImplementedError) as error:
        raise refuse(f"a truncated or corrupt .npz archive: {one_line(error)}") from None


class _MemberReader:
    """Checks a member's npy header against its zip entry and its :class:`Member`, then reads it."""

    def __init__(self, archive: zipfile.ZipFile, path: Path, error_type: type[Exception], what: str):
        self.archive, self.path, self.error_type, self.what = archive, path, error_type, what

    def declared(self, info: zipfile.ZipInfo, member: Member) -> int:
        """Bytes the member's header declares, once they fit its entry and ``member`` allows them."""
        name = info.filename[: -len(".npy")]
        with self.archive.open(info) as handle:
            version = np.lib.format.read_magic(handle)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(handle)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
            else:
                raise self._bad(name, f"npy format version {version[0]}.{version[1]} is not read")
            header = handle.tell()
        if dtype.hasobject:
            raise self.error_type(f"{self.path} is not a vbrl_ros {self.what} file (it holds pickled "
                                  f"object arrays, which are never loaded: allow_pickle=False)")
        nbytes = math.prod(shape) * dtype.itemsize
        if dtype.kind not in member.kinds or len(shape) != member.ndim:
            raise self._bad(name, f"it holds {_array_kind(shape, dtype)}, where the {self.what} "
                                  f"format stores {member.describe()}")
        if header + nbytes != info.file_size or info.compress_size > self.path.stat().st_size:
            declared, held = _sizes(nbytes, max(info.file_size - header, 0))
            raise self._bad(name, f"its header declares {_array_kind(shape, dtype)} ({declared}) "
                                  f"but the archive holds {held} for it")
        return nbytes

    def read(self, name: str, info: zipfile.ZipInfo | None, member: Member) -> np.ndarray | None:
        if info is None:
            return None
        self.declared(info, member)
        with self.archive.open(info) as handle:
            return np.lib.format.read_array(handle, allow_pickle=False)

    def _bad(self, name: str, reason: str) -> Exception:
        return self.error_type(f"{self.path} has a bad '{name}': {reason}")


def _array_kind(shape: tuple[int, ...], dtype: np.dtype) -> str:
    if not shape:
        return f"a single {dtype} value"
    article = "an" if str(dtype)[0] in "aeiou" else "a"  # an int64, a float32
    return f"{article} {dtype} array of shape {shape}"


def _sizes(a: int, b: int) -> tuple[str, str]:
    """Two sizes that differ, each as :func:`_size` says it unless that makes them look alike."""
    rounded = _size(a), _size(b)
    return rounded if rounded[0] != rounded[1] else (f"{a} bytes", f"{b} bytes")


def _size(nbytes: int) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.1f} {unit}"
    return f"{nbytes} bytes"


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


def _foreign_format(tag: str | None, names: list[str], expected: str) -> str:
    """Why an ``.npz`` holding ``names`` without the ``format`` tag ``expected`` is another file, in a few words."""
    if tag is not None:
        return f"its format tag is '{tag}', not '{expected}'"
    names = sorted(names)
    listed = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
    return f"an .npz without the format tag '{expected}'; it holds {listed or 'no arrays'}"
