import numpy as np
import pytest

from vbrl_ros.io.npz import one_line, read_npz


class Refused(ValueError):
    pass


def test_reads_arrays(tmp_path):
    np.savez(tmp_path / "a.npz", x=np.arange(3))
    assert read_npz(tmp_path / "a.npz", Refused, "thing")["x"].tolist() == [0, 1, 2]


@pytest.mark.parametrize("content, match", [
    (None, "thing file .* does not exist"),
    (b"not a zip", "not a readable .npz thing"),
])
def test_unreadable_files_raise_the_callers_error_in_one_line(tmp_path, content, match):
    path = tmp_path / "a.npz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(Refused, match=match) as error:
        read_npz(path, Refused, "thing")
    assert "\n" not in str(error.value)


def test_pickled_arrays_are_refused(tmp_path):
    np.savez(tmp_path / "p.npz", x=np.array([{"a": 1}], dtype=object))
    with pytest.raises(Refused, match="allow_pickle=False"):
        read_npz(tmp_path / "p.npz", Refused, "thing")


def test_one_line_joins_lines():
    assert one_line(ValueError("a\n  b")) == "a b" and one_line(ValueError()) == "ValueError"
