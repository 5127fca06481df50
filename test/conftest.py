"""The ``--long`` option, and fixtures for the tests that read the package's structure: its modules, from the tree."""

from __future__ import annotations

import pkgutil
from collections.abc import Iterator
from pathlib import Path

import pytest

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "vbrl_ros"
#: Top-level names of ROS 2 Python packages (rclpy and message/interface packages).
ROS_PACKAGES = (
    "rclpy", "sensor_msgs", "std_msgs", "nav_msgs", "geometry_msgs", "diagnostic_msgs",
    "visualization_msgs", "std_srvs", "rcl_interfaces", "rosidl_runtime_py", "builtin_interfaces",
    "rosgraph_msgs", "rosidl_parser", "tf2_msgs",
)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--long", action="store_true",
                     help="run the reliability fuzz at full length (10k messages, 1k file mutations)")


@pytest.fixture(scope="session")
def long_run(request: pytest.FixtureRequest) -> bool:
    """True with ``--long``: fuzz tests run for as long as a local check deserves, not CI's minute."""
    return bool(request.config.getoption("--long"))


def _modules(directory: Path, prefix: str) -> Iterator[tuple[str, Path]]:
    for info in pkgutil.iter_modules([str(directory)]):  # reads the directory, imports nothing
        name = f"{prefix}.{info.name}"
        if info.ispkg:
            yield name, directory / info.name / "__init__.py"
            yield from _modules(directory / info.name, name)
        else:
            yield name, directory / f"{info.name}.py"


@pytest.fixture(scope="session")
def package_modules() -> dict[str, Path]:
    """Every module of vbrl_ros (packages by their ``__init__.py``) -> its file."""
    return {"vbrl_ros": PACKAGE_DIR / "__init__.py", **dict(_modules(PACKAGE_DIR, "vbrl_ros"))}


@pytest.fixture(scope="session")
def ros_packages() -> tuple[str, ...]:
    return ROS_PACKAGES


@pytest.fixture
def expected_yaws(monkeypatch: pytest.MonkeyPatch) -> list:
    """The ``expected_yaw`` each verification in this test was told, in order: the real
    :meth:`QueryVerifier.verify` runs, its argument noted."""
    from vbrl_ros.detection.registration import QueryVerifier

    told: list = []
    register = QueryVerifier.verify

    def listening(self, match, **options):
        told.append(options.get("expected_yaw"))
        return register(self, match, **options)

    monkeypatch.setattr(QueryVerifier, "verify", listening)
    return told
