"""The ``--long`` option (which also lifts the per-test timeout), a backstop for tests stuck in C++,
and fixtures for the tests that read the package's structure: its modules, from the tree."""

from __future__ import annotations

import faulthandler
import pkgutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from pytest_timeout import get_env_settings

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


#: Seconds after setup.cfg's timeout at which a test still running ends its process.
BACKSTOP_S = 120


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # setup.cfg's per-test timeout catches hangs in the default run; --long runs for as long as it takes
    if config.getoption("--long"):
        for item in items:
            item.add_marker(pytest.mark.timeout(0))


@pytest.fixture(autouse=True)
def hang_backstop(request: pytest.FixtureRequest) -> Iterator[None]:
    """pytest-timeout's signal reaches Python code and blocking calls, not a thread stuck inside C++
    (DDS): past the timeout and a margin, every thread's stack is printed and the process ends."""
    marker = request.node.get_closest_marker("timeout")
    # as pytest-timeout reads it: the marker, else --timeout, PYTEST_TIMEOUT or setup.cfg
    timeout = marker.args[0] if marker and marker.args else get_env_settings(request.config).timeout
    timeout = float(timeout or 0)
    if timeout <= 0:
        yield
        return
    faulthandler.dump_traceback_later(timeout + BACKSTOP_S, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


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
