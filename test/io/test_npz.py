import pickle
import struct
import tracemalloc
import zipfile

import numpy as np
import pytest

from vbrl_ros.io.npz import TEXT, Member, one_line, read_npz


class Refused(ValueError):
    pass


TAG = "test.thing"
MEMBERS = {"format": TEXT, "x": Member("iu", 1), "name": TEXT}


def read(path):
    return read_npz(path, Refused, "thing", TAG, MEMBERS)


def save(path, **arrays):
    np.savez(path, format=np.array(TAG), **arrays)
    return path


def test_reads_the_defined_arrays(tmp_path):
    contents = read(save(tmp_path / "a.npz", x=np.arange(3), name=np.array("n")))
    assert contents["x"].tolist() == [0, 1, 2] and str(contents["name"]) == "n"


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
        read(path)
    assert "\n" not in str(error.value)


def test_a_directory_or_a_device_is_not_called_missing(tmp_path):
    with pytest.raises(Refused, match=f"thing file {tmp_path} is a directory$"):
        read(tmp_path)
    with pytest.raises(Refused, match="thing file /dev/null is not a regular file$"):
        read("/dev/null")


def test_a_plain_zip_is_not_an_npz(tmp_path):
    with zipfile.ZipFile(tmp_path / "a.npz", "w") as archive:
        archive.writestr("notes.txt", "hello")
    with pytest.raises(Refused, match="a zip archive, not an .npz: 'notes.txt'"):
        read(tmp_path / "a.npz")


def test_another_format_names_its_tag_or_its_arrays(tmp_path):
    np.savez(tmp_path / "other.npz", format=np.array("other.thing"))
    with pytest.raises(Refused, match=r"\(its format tag is 'other.thing', not 'test.thing'\)$"):
        read(tmp_path / "other.npz")
    np.savez(tmp_path / "plain.npz", b=np.ones(1), a=np.ones(1))
    with pytest.raises(Refused, match=r"without the format tag 'test.thing'; it holds a, b\)$"):
        read(tmp_path / "plain.npz")


@pytest.mark.parametrize("name, value, held", [
    ("x", np.array("abc"), "a single <U3 value"),
    ("x", np.ones((2, 2), np.int64), "an int64 array of shape (2, 2)"),
    ("x", np.ones(3), "a float64 array of shape (3,)"),
    ("name", np.array(5), "a single int64 value"),
    ("name", np.array(["a", "b"]), "a <U1 array of shape (2,)"),
])
def test_a_member_of_the_wrong_kind_is_named(tmp_path, name, value, held):
    path = save(tmp_path / "a.npz", **{name: value})
    expected = {"x": "a 1-d integer array", "name": "a text string"}[name]
    with pytest.raises(Refused) as error:
        read(path)
    assert str(error.value) == f"{path} has a bad '{name}': it holds {held}, where the thing format stores {expected}"


def npy_header(shape, descr="<i8") -> bytes:
    text = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode("latin1")
    text += b" " * (-(len(text) + 11) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text


def test_a_header_claiming_more_than_its_entry_holds_is_refused_unread(tmp_path):
    path = save(tmp_path / "a.npz")
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("x.npy", npy_header((10**12,)) + np.arange(3).tobytes())
    tracemalloc.start()
    try:
        with pytest.raises(Refused) as error:
            read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(error.value) == (f"{path} has a bad 'x': its header declares an int64 array of shape "
                                f"(1000000000000,) (8.0 TB) but the archive holds 24 bytes for it")
    assert peak < 1e6


def add_compressed_zeros(path, name, rows):
    """``rows`` int64 zeros under ``name``, deflated: a few hundred kB on disk per 100 MB."""
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open(f"{name}.npy", "w", force_zip64=True) as out:
            out.write(npy_header((rows,)))
            for _ in range(rows * 8 >> 20):
                out.write(bytes(1 << 20))


def peak_bytes_reading(path):
    tracemalloc.start()
    try:
        try:
            result = read(path)
        except Refused as error:
            result = error
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_compressed_zeros_are_refused_under_a_defined_name_and_never_read_under_another(tmp_path):
    rows = 30 << 20  # 240 MB of int64 zeros, 0.25 MB deflated
    defined = save(tmp_path / "defined.npz")
    add_compressed_zeros(defined, "x", rows)
    error, peak = peak_bytes_reading(defined)
    assert isinstance(error, Refused) and peak < 1e6
    assert str(error) == (f"{defined} declares 251.7 MB of arrays in a {defined.stat().st_size / 1e3:.1f} kB file "
                          "(more than 20 times its size): refused unread, as a compressed bomb would be")

    extra = save(tmp_path / "extra.npz", x=np.arange(3))
    add_compressed_zeros(extra, "extra", rows)
    contents, peak = peak_bytes_reading(extra)
    assert sorted(contents) == ["format", "x"] and peak < 1e6


class Payload:
    """Unpickling this creates ``marker``: a file that would prove the pickle ran."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def add_pickle(path, name, marker):
    array = np.array([Payload(marker)], dtype=object)
    with zipfile.ZipFile(path, "a") as archive:
        with archive.open(f"{name}.npy", "w") as out:
            np.lib.format.write_array(out, array, allow_pickle=True)
    assert pickle.loads(pickle.dumps(Payload(marker))) and marker.exists()  # the payload does work
    marker.unlink()


def test_pickled_members_are_refused_or_ignored_never_run(tmp_path):
    marker = tmp_path / "pickle_ran"
    defined = save(tmp_path / "defined.npz")
    add_pickle(defined, "x", marker)
    with pytest.raises(Refused, match="pickled object arrays, which are never loaded: allow_pickle=False"):
        read(defined)
    extra = save(tmp_path / "extra.npz", x=np.arange(2))
    add_pickle(extra, "payload", marker)
    assert sorted(read(extra)) == ["format", "x"]
    assert not marker.exists()


def test_one_line_joins_lines():
    assert one_line(ValueError("a\n  b")) == "a b" and one_line(ValueError()) == "ValueError"


def test_sizes_that_differ_never_read_alike(tmp_path):
    path = save(tmp_path / "a.npz")
    with zipfile.ZipFile(path, "a") as archive:
        archive.writestr("x.npy", npy_header((1_000_000,)) + bytes(7_999_992))  # one element short
    with pytest.raises(Refused, match=r"\(8000000 bytes\) but the archive holds 7999992 bytes for it$"):
        read(path)
