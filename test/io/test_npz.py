import zipfile

import numpy as np
import pytest

from vbrl_ros.io.npz import foreign_format, one_line, read_npz


class Refused(ValueError):
    pass


def test_reads_arrays(tmp_path):
    np.savez(tmp_path / "a.npz", x=np.arange(3))
    assert read_npz(tmp_path / "a.npz", Refused, "thing")["x"].tolist() == [0, 1, 2]


@pytest.mark.parametrize("content, match", [
    (None, "thing file .* does not exist"),
    (b"not a zip", "is not a vbrl_ros thing file .it is a text file"),
    (b"", "it is empty"),
    (b"\x93NUMPY\x01\x00", "a single .npy array"),
    (bytes(range(256)), r"\(not an .npz archive\)"),
    (b"PK\x03\x04cut short", "truncated or corrupt"),
])
def test_unreadable_files_raise_the_callers_error_in_one_line(tmp_path, content, match):
    path = tmp_path / "a.npz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(Refused, match=match) as error:
        read_npz(path, Refused, "thing")
    assert "\n" not in str(error.value)


def test_a_plain_zip_is_not_an_npz(tmp_path):
    with zipfile.ZipFile(tmp_path / "a.npz", "w") as archive:
        archive.writestr("notes.txt", "hello")
    with pytest.raises(Refused, match="a zip archive, not an .npz: 'notes.txt'"):
        read_npz(tmp_path / "a.npz", Refused, "thing")


def test_foreign_format_names_the_tag_or_the_arrays():
    assert foreign_format({"format": np.array("other.thing")}, "mine") == \
        "its format tag is 'other.thing', not 'mine'"
    assert foreign_format({"b": np.ones(1), "a": np.ones(1)}, "mine") == \
        "an .npz without the format tag 'mine'; it holds a, b"


def test_pickled_arrays_are_refused(tmp_path):
    np.savez(tmp_path / "p.npz", x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(Refused, match="allow_pickle=False"):
        read_npz(tmp_path / "p.npz", Refused, "thing")


def test_one_line_joins_lines():
    assert one_line(ValueError("a\n  b")) == "a b" and one_line(ValueError()) == "ValueError"
