"""PointCloud2 <-> numpy: driver-style layouts round-trip exactly, bad messages raise PointCloud2Error.

Messages here are built by an independent, struct-based packer (one
struct.pack_into per value), so decoding is not only checked against our
own encoder.
"""

from __future__ import annotations

import struct
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vbrl_ros.io.pointcloud2 import (
    DATATYPE_TO_NUMPY,
    PointCloud2Error,
    encode_cloud,
    read_points,
    read_structured,
    read_xyz_intensity,
    split_stamp,
    to_rosbags_msg,
)
from vbrl_ros.ros.message_conversion import to_ros_msg

STRUCT_CODE = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
EXTRA_FIELD_NAMES = ["intensity", "ring", "time", "reflectivity", "ambient", "t"]
pytestmark = pytest.mark.filterwarnings("error")  # decoding must not warn per message (a node would spam)
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def random_values(rng: np.random.Generator, datatype: int, shape: tuple[int, ...]) -> np.ndarray:
    dtype = np.dtype(DATATYPE_TO_NUMPY[datatype])
    if dtype.kind == "f":
        values = rng.normal(0.0, 50.0, size=shape).astype(dtype)
        values[rng.random(shape) < 0.15] = np.nan
        values[rng.random(shape) < 0.05] = np.inf
        return values
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dtype)


@st.composite
def cloud_layouts(draw: st.DrawFn) -> dict:
    """A driver-like cloud: shuffled fields, extra fields, gaps, padding, rows, byte order."""
    coordinate_type = draw(st.sampled_from([7, 8]))
    fields = [(axis, coordinate_type, 1) for axis in "xyz"]
    for name in draw(st.lists(st.sampled_from(EXTRA_FIELD_NAMES), unique=True, max_size=4)):
        count = 1 if name == "intensity" else draw(st.integers(1, 3))
        fields.append((name, draw(st.integers(1, 8)), count))
    fields = draw(st.permutations(fields))
    specs, offset = [], 0
    for name, datatype, count in fields:
        offset += draw(st.integers(0, 3))  # gaps make unaligned offsets, as packed drivers do
        specs.append(SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count))
        offset += np.dtype(DATATYPE_TO_NUMPY[datatype]).itemsize * count
    return {
        "fields": specs,
        "point_step": offset + draw(st.integers(0, 9)),
        "height": draw(st.integers(1, 3)),
        "width": draw(st.integers(0, 6)),
        "row_padding": draw(st.integers(0, 7)),
        "big_endian": draw(st.booleans()),
        "seed": draw(st.integers(0, 2**32 - 1)),
    }


def build_cloud(layout: dict) -> tuple[SimpleNamespace, dict[str, np.ndarray]]:
    """Pack random values value-by-value with struct; return (message, values per field (H, W, count))."""
    rng = np.random.default_rng(layout["seed"])
    height, width, step = layout["height"], layout["width"], layout["point_step"]
    row_step = width * step + layout["row_padding"]
    order = ">" if layout["big_endian"] else "<"
    values = {f.name: random_values(rng, f.datatype, (height, width, f.count)) for f in layout["fields"]}
    data = bytearray(rng.integers(0, 256, size=row_step * height, dtype=np.uint8).tobytes())  # junk padding
    for row in range(height):
        for col in range(width):
            for f in layout["fields"]:
                code = order + STRUCT_CODE[f.datatype] * f.count
                struct.pack_into(code, data, row * row_step + col * step + f.offset, *values[f.name][row, col].tolist())
    msg = SimpleNamespace(
        height=height, width=width, fields=layout["fields"], is_bigendian=layout["big_endian"],
        point_step=step, row_step=row_step, data=bytes(data), is_dense=False,
    )
    return msg, values


def assert_bitwise_equal(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.dtype == expected.dtype
    assert actual.tobytes() == np.ascontiguousarray(expected).tobytes()


@FAST
@given(cloud_layouts())
def test_decoding_driver_layouts_is_exact(layout: dict) -> None:
    msg, values = build_cloud(layout)
    n = layout["height"] * layout["width"]
    structured = read_structured(msg)
    assert structured.shape == (n,)
    for name, expected in values.items():
        assert_bitwise_equal(structured[name], expected.reshape(structured[name].shape))

    xyz = read_points(msg)
    expected_xyz = np.stack([values[a].reshape(n) for a in "xyz"], axis=1).astype(np.float64)
    np.testing.assert_array_equal(xyz, expected_xyz)
    np.testing.assert_array_equal(read_points(msg, skip_nans=True), expected_xyz[~np.isnan(expected_xyz).any(axis=1)])

    points, intensity = read_xyz_intensity(msg)
    returns = np.isfinite(expected_xyz).all(axis=1) & (expected_xyz != 0).any(axis=1)
    np.testing.assert_array_equal(points, expected_xyz[returns])
    assert points.dtype == np.float64 and points.shape == (returns.sum(), 3)
    if "intensity" in values:
        np.testing.assert_array_equal(intensity, values["intensity"].reshape(n).astype(np.float64)[returns])
    else:
        assert intensity is None


@FAST
@given(cloud_layouts())
def test_encode_then_decode_round_trips(layout: dict) -> None:
    _, values = build_cloud(layout)
    dtype = np.dtype([(f.name, DATATYPE_TO_NUMPY[f.datatype], (f.count,)) if f.count > 1
                      else (f.name, DATATYPE_TO_NUMPY[f.datatype]) for f in layout["fields"]])
    grid = np.empty((layout["height"], layout["width"]), dtype=dtype)
    for name, field_values in values.items():
        grid[name] = field_values.reshape(grid[name].shape)
    packed_size = dtype.itemsize
    cloud = encode_cloud(grid, point_step=packed_size + layout["point_step"] % 5,
                         row_padding=layout["row_padding"], big_endian=layout["big_endian"])
    msg = SimpleNamespace(fields=cloud.fields, data=cloud.data, point_step=cloud.point_step, row_step=cloud.row_step,
                          height=cloud.height, width=cloud.width, is_bigendian=cloud.is_bigendian)
    assert [f.name for f in cloud.fields] == list(dtype.names)
    assert cloud.is_dense == all(np.isfinite(values[a]).all() for a in "xyz")
    decoded = read_structured(msg)
    for name in dtype.names:
        assert_bitwise_equal(decoded[name], grid[name].reshape(decoded[name].shape))


def test_plain_array_encoding_converts_datatypes() -> None:
    points = np.array([[1.5, -2.0, 3.25, 7.0], [np.nan, 0.0, 1.0, 2.0]])
    cloud = encode_cloud(points, ["x", "y", "z", "intensity"], datatypes=7)
    assert [f.datatype for f in cloud.fields] == [7] * 4 and cloud.point_step == 16 and not cloud.is_dense
    msg = SimpleNamespace(**cloud._asdict())
    np.testing.assert_array_equal(read_points(msg, ("x", "y", "z", "intensity")), points)
    with pytest.raises(ValueError, match="field names"):
        encode_cloud(points, ["x", "y", "z"])
    with pytest.raises(ValueError, match="duplicate"):
        encode_cloud(points, ["x", "y", "z", "x"])


def test_no_return_placeholders_are_dropped_with_their_intensity() -> None:
    """Ouster and Livox drivers write (0, 0, 0) where a beam got no return; a point with only
    some coordinates zero is a return."""
    points = np.array([[0.0, 0.0, 0.0, 5.0], [0.0, 2.0, -1.0, 6.0], [3.0, 0.0, 0.0, 7.0],
                       [0.0, 0.0, 0.0, 0.0], [-0.0, 0.0, -0.0, 8.0], [1.0, 1.0, 1.0, 9.0]])
    msg = SimpleNamespace(**encode_cloud(points, ["x", "y", "z", "intensity"], datatypes=7)._asdict())
    xyz, intensity = read_xyz_intensity(msg)
    np.testing.assert_array_equal(xyz, points[[1, 2, 5], :3])
    np.testing.assert_array_equal(intensity, [6.0, 7.0, 9.0])


def test_rclpy_messages_round_trip() -> None:
    sensor_msgs = pytest.importorskip("sensor_msgs.msg")
    layout = {"fields": [SimpleNamespace(name="intensity", offset=0, datatype=2, count=1),
                         SimpleNamespace(name="z", offset=1, datatype=8, count=1),
                         SimpleNamespace(name="x", offset=9, datatype=8, count=1),
                         SimpleNamespace(name="y", offset=17, datatype=8, count=1),
                         SimpleNamespace(name="ring", offset=26, datatype=4, count=1)],
              "point_step": 32, "height": 4, "width": 5, "row_padding": 6, "big_endian": True, "seed": 1}
    reference, values = build_cloud(layout)
    msg = sensor_msgs.PointCloud2()
    msg.height, msg.width, msg.point_step, msg.row_step = 4, 5, 32, reference.row_step
    msg.is_bigendian = True
    msg.fields = [sensor_msgs.PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
                  for f in layout["fields"]]
    msg.data = reference.data
    np.testing.assert_array_equal(read_points(msg, ("ring",))[:, 0], values["ring"].reshape(-1))
    np.testing.assert_array_equal(read_structured(msg)["x"], values["x"].reshape(-1))

    points = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    built = to_ros_msg(points, ["x", "y", "z", "intensity"], stamp=(1_700_000_000, 5), frame_id="os_lidar")
    assert isinstance(built, sensor_msgs.PointCloud2)
    assert (built.header.stamp.sec, built.header.stamp.nanosec, built.header.frame_id) == (1_700_000_000, 5, "os_lidar")
    xyz, intensity = read_xyz_intensity(built)
    np.testing.assert_array_equal(xyz, points[:, :3].astype(np.float64))
    np.testing.assert_array_equal(intensity, points[:, 3].astype(np.float64))


@pytest.mark.parametrize("store", ["ROS2_JAZZY", "ROS1_NOETIC"])
@settings(max_examples=15, deadline=None)
@given(layout=cloud_layouts())
def test_rosbags_serialised_messages_round_trip(store: str, layout: dict) -> None:
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(getattr(Stores, store))
    reference, values = build_cloud(layout)
    types = typestore.types
    header = types["std_msgs/msg/Header"](
        **({"seq": 3} if store == "ROS1_NOETIC" else {}),
        stamp=types["builtin_interfaces/msg/Time"](sec=10, nanosec=20), frame_id="lidar")
    fields = [types["sensor_msgs/msg/PointField"](name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
              for f in reference.fields]
    msg = types["sensor_msgs/msg/PointCloud2"](
        header=header, height=reference.height, width=reference.width, fields=fields,
        is_bigendian=reference.is_bigendian, point_step=reference.point_step, row_step=reference.row_step,
        data=np.frombuffer(reference.data, dtype=np.uint8), is_dense=False)
    if store == "ROS1_NOETIC":
        decoded_msg = typestore.deserialize_ros1(typestore.serialize_ros1(msg, msg.__msgtype__), msg.__msgtype__)
    else:
        decoded_msg = typestore.deserialize_cdr(typestore.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    assert isinstance(decoded_msg.data, np.ndarray)
    decoded = read_structured(decoded_msg)
    for name, expected in values.items():
        assert_bitwise_equal(decoded[name], expected.reshape(decoded[name].shape))

    rebuilt = to_rosbags_msg(decoded, typestore=typestore, stamp=12.25, frame_id="lidar")
    assert (rebuilt.header.stamp.sec, rebuilt.header.stamp.nanosec) == (12, 250_000_000)
    for name in values:
        assert_bitwise_equal(read_structured(rebuilt)[name], decoded[name])


# --------------------------------------------------------------------------- malformed messages


def valid_message() -> SimpleNamespace:
    msg, _ = build_cloud({"fields": [SimpleNamespace(name=n, offset=4 * i, datatype=7, count=1)
                                     for i, n in enumerate(["x", "y", "intensity", "z"])],
                          "point_step": 16, "height": 2, "width": 3, "row_padding": 0, "big_endian": False, "seed": 0})
    return msg


def field(name: str = "x", offset: int = 0, datatype: int = 7, count: int = 1) -> SimpleNamespace:
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=count)


MALFORMATIONS = {
    "no z field": dict(fields=[field("x", 0), field("y", 4), field("intensity", 8)]),
    "data shorter than row_step*height": dict(data=bytes(16 * 3 * 2 - 1)),
    "zero point_step": dict(point_step=0),
    "field beyond point_step": dict(fields=[field("x", 0), field("y", 4), field("z", 12, datatype=8)]),
    "unknown datatype": dict(fields=[field("x", 0), field("y", 4), field("z", 8, datatype=9)]),
    "count zero": dict(fields=[field("x", 0), field("y", 4), field("z", 8, count=0)]),
    "row_step below width*point_step": dict(row_step=47),
    "negative width": dict(width=-1),
    "duplicate field": dict(fields=[field("x", 0), field("y", 4), field("z", 8), field("z", 12)]),
    "data not bytes": dict(data=object()),
    "fields not a list": dict(fields=7),
    "field name not a string": dict(fields=[field(None, 0)]),
    "missing attribute": dict(height=None),
}


@pytest.mark.parametrize("name", MALFORMATIONS)
def test_malformed_messages_raise_one_line_error(name: str) -> None:
    msg = valid_message()
    for key, value in MALFORMATIONS[name].items():
        setattr(msg, key, value)
    if name == "missing attribute":
        del msg.height
    readers = [read_points, read_xyz_intensity] + ([read_structured] if name != "no z field" else [])
    for reader in readers:
        with pytest.raises(PointCloud2Error) as info:
            reader(msg)
        assert "\n" not in str(info.value) and str(info.value)
    assert isinstance(info.value, ValueError)


def test_missing_field_error_names_the_fields() -> None:
    msg = valid_message()
    msg.fields = [field("x", 0), field("y", 4), field("intensity", 8)]
    with pytest.raises(PointCloud2Error, match=r"no 'z' field \(fields: x, y, intensity\)"):
        read_xyz_intensity(msg)
    msg.fields = [field("x\ny", 0)]  # a line break in a field name must not break the log line
    with pytest.raises(PointCloud2Error, match=r"fields: x\\ny\)$") as info:
        read_points(msg)
    assert "\n" not in str(info.value)


anything = st.one_of(st.none(), st.booleans(), st.integers(-(2**40), 2**40), st.floats(), st.text(max_size=3),
                     st.binary(max_size=64))
small_int = st.one_of(st.integers(-3, 40), anything)


@settings(max_examples=300, deadline=None)
@given(
    height=small_int, width=small_int, point_step=small_int, row_step=st.one_of(st.integers(-3, 200), anything),
    is_bigendian=st.one_of(st.booleans(), anything),
    fields=st.one_of(anything, st.lists(st.builds(SimpleNamespace, name=st.one_of(st.sampled_from("xyzi"), anything),
                                                  offset=small_int, datatype=small_int, count=small_int), max_size=5)),
    data=st.one_of(st.binary(max_size=400), anything, st.lists(st.integers(-5, 300), max_size=50)),
    requested=st.sampled_from([("x", "y", "z"), ("i",), ()]),
)
def test_random_messages_raise_only_pointcloud2_error(height, width, point_step, row_step, is_bigendian, fields,
                                                      data, requested) -> None:
    msg = SimpleNamespace(height=height, width=width, point_step=point_step, row_step=row_step,
                          is_bigendian=is_bigendian, fields=fields, data=data)
    for reader in (lambda m: read_points(m, requested), read_structured, read_xyz_intensity):
        try:
            result = reader(msg)
        except PointCloud2Error as error:
            assert "\n" not in str(error)
            continue
        assert len(result if isinstance(result, np.ndarray) else result[0]) == int(height) * int(width) or \
            reader is read_xyz_intensity


@settings(max_examples=200, deadline=None)
@given(layout=cloud_layouts(), target=st.sampled_from(["height", "width", "point_step", "row_step", "data", "offset",
                                                       "datatype", "count", "name"]),
       value=st.integers(-4, 120), field_index=st.integers(0, 7))
def test_mutated_driver_clouds_raise_only_pointcloud2_error(layout: dict, target: str, value: int,
                                                            field_index: int) -> None:
    msg, _ = build_cloud(layout)
    msg.fields = [SimpleNamespace(**vars(f)) for f in msg.fields]
    if target == "data":
        msg.data = msg.data[: max(value, 0)]
    elif target in ("offset", "datatype", "count", "name"):
        setattr(msg.fields[field_index % len(msg.fields)], target, value if target != "name" else str(value))
    else:
        setattr(msg, target, value)
    for reader in (read_points, read_structured, read_xyz_intensity):
        try:
            reader(msg)
        except PointCloud2Error as error:
            assert "\n" not in str(error)


@pytest.mark.parametrize(("stamp", "expected"), [(1.5, (1, 500_000_000)), ((3, 2_000_000_001), (5, 1)),
                                                 (1_630_577_758.56949, (1_630_577_758, 569_490_000)), (-0.25, (-1, 750_000_000))])
def test_split_stamp(stamp, expected) -> None:
    sec, nanosec = split_stamp(stamp)
    assert sec == expected[0] and abs(nanosec - expected[1]) < 1_000  # float Unix times carry ~0.2 µs
