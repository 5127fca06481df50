"""Helpers for tests and tools that run real DDS (Fast DDS through rclpy), isolated from everything else.

Typical test::

    with ros_context() as context:                       # private rclpy Context, fresh domain id
        env = isolated_ros_env(context.get_domain_id())  # same domain for a subprocess
        node = rclpy.create_node("probe", context=context)
        with MessageCollector(node, {"/points": PointCloud2}) as collector:
            process = subprocess.Popen([...], env=env)
            collector.wait_for({"/points": 10}, timeout=20)

Isolation: every call of :func:`unique_domain_id` gives a new ``ROS_DOMAIN_ID``
in 1..101 (0 is everyone's default; above 101 Fast DDS ports may collide
with Linux ephemeral ports), discovery is limited to this host, and pytest-
xdist workers of one run never share an id (each has its own block). Domain ids are few, so two
unrelated processes on one host can still draw the same one; that is harmless
unless both publish the same topics at the same time.
"""

from __future__ import annotations

import itertools
import os
import re
import time
import zlib
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Mapping

DOMAIN_IDS = 101  # usable ids are 1..DOMAIN_IDS
ISOLATION_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
# Variables that would widen or contradict LOCALHOST discovery.
CONFLICTING_ENV = ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS")

_calls = itertools.count()


def unique_domain_id() -> int:
    """A ROS domain id in 1..101 not used by a recent call in this process, nor ever by another xdist worker.

    Under pytest-xdist, worker ``gwK`` of ``n`` cycles through its own block of
    ``101 // n`` ids (started at a hash of the run's id, so two concurrent runs
    differ too): however many DDS tests a worker runs, its ids never meet another
    worker's, and one reused by the same worker belongs to a test that has ended.
    Outside xdist the sequence starts at an offset derived from the pid.
    """
    call = next(_calls)
    worker = re.fullmatch(r"gw(\d+)", os.environ.get("PYTEST_XDIST_WORKER", ""))
    if worker:
        index = int(worker.group(1))
        workers = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0), index + 1)
        block = max(1, DOMAIN_IDS // workers)
        offset = zlib.crc32(os.environ.get("PYTEST_XDIST_TESTRUNUID", "").encode())
        return 1 + (index * block + (offset + call) % block) % DOMAIN_IDS
    offset = zlib.crc32(str(os.getpid()).encode())
    return 1 + (offset + call) % DOMAIN_IDS


def isolated_ros_env(domain_id: int | None = None, base: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default ``os.environ``) for a subprocess on an isolated, host-local domain.

    Sets ``ROS_DOMAIN_ID`` (``domain_id`` or a fresh :func:`unique_domain_id`),
    ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``.
    """
    if domain_id is not None and not 0 <= domain_id <= 232:
        raise ValueError(f"ROS domain id must be in 0..232, got {domain_id}")
    env = {key: value for key, value in (os.environ if base is None else base).items() if key not in CONFLICTING_ENV}
    env.update(ISOLATION_ENV, ROS_DOMAIN_ID=str(unique_domain_id() if domain_id is None else domain_id))
    return env


@contextmanager
def ros_context(domain_id: int | None = None) -> Iterator[Any]:
    """rclpy initialised in a private ``rclpy.Context`` on ``domain_id`` (default: fresh), shut down on exit.

    The discovery range and RMW variables are set in this process's
    environment too, since rcl reads them at init; they stay set afterwards
    (harmless, and other contexts of the process want the same). rclpy's
    signal handlers are not installed: Ctrl-C stays a plain KeyboardInterrupt.
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    for key in CONFLICTING_ENV:
        os.environ.pop(key, None)
    os.environ.update(ISOLATION_ENV)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=unique_domain_id() if domain_id is None else domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield context
    finally:
        context.try_shutdown()


def spin_until(node: Any, predicate: Callable[[], bool], timeout: float, *, executor: Any = None) -> bool:
    """Spin ``node`` (in ``executor`` or a temporary one) until ``predicate()`` is true; False on timeout."""
    from rclpy.executors import SingleThreadedExecutor

    own = executor is None
    if own:
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
    try:
        deadline = time.monotonic() + timeout
        while not predicate():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            executor.spin_once(timeout_sec=min(remaining, 0.05))
        return True
    finally:
        if own:
            executor.remove_node(node)
            executor.shutdown()


class MessageCollector:
    """Subscribes to several topics at once and keeps every message with its (monotonic) arrival time
    and the publisher's send time (``sent``: DDS source timestamp, s).

    Subscribe before the publisher starts: volatile publishers do not resend
    what a late subscriber missed. The default QoS is reliable with a deep
    history (1000), so a burst is not thinned by keep-last while the test is
    busy; pass ``qos`` (e.g. ``rclpy.qos.qos_profile_sensor_data``) to test
    other profiles.
    """

    def __init__(self, node: Any, topics: Mapping[str, type], qos: Any = None) -> None:
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile

        self.node = node
        self.messages: dict[str, list[Any]] = {topic: [] for topic in topics}
        self.arrivals: dict[str, list[float]] = {topic: [] for topic in topics}
        # when the publisher sent each message: unlike arrivals, not bunched by late discovery or a
        # busy test thread, so it is what a pacing test should read
        self.sent: dict[str, list[float]] = {topic: [] for topic in topics}
        qos = QoSProfile(depth=1000) if qos is None else qos
        self._subscriptions = [node.create_subscription(msg_type, topic, self._callback(topic), qos)
                               for topic, msg_type in topics.items()]
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)

    def _callback(self, topic: str) -> Callable[[Any], None]:
        def store(msg: Any, info: Any) -> None:
            self.arrivals[topic].append(time.monotonic())
            self.sent[topic].append(info["source_timestamp"] * 1e-9)
            self.messages[topic].append(msg)

        return store

    def count(self, topic: str) -> int:
        return len(self.messages[topic])

    def spin_until(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Spin until ``predicate()`` is true (True) or ``timeout`` s pass (False)."""
        return spin_until(self.node, predicate, timeout, executor=self.executor)

    def wait_for(self, counts: Mapping[str, int], timeout: float) -> bool:
        """Spin until each topic has at least ``counts[topic]`` messages; False on timeout."""
        return self.spin_until(lambda: all(self.count(topic) >= n for topic, n in counts.items()), timeout)

    def close(self) -> None:
        """Remove the subscriptions and the executor (idempotent); the node stays."""
        for subscription in self._subscriptions:
            self.node.destroy_subscription(subscription)
        self._subscriptions = []
        if self.executor is not None:
            self.executor.remove_node(self.node)
            self.executor.shutdown()
            self.executor = None

    def __enter__(self) -> MessageCollector:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def diagnostics_values(array: Any) -> dict[str, float]:
    """The values of a ``DiagnosticArray``'s first status by key, as numbers (vbrl_node's all are)."""
    return {kv.key: float(kv.value) for kv in array.status[0].values}


def collect_messages(node: Any, topic: str, msg_type: type, count: int, timeout: float, qos: Any = None) -> list[Any]:
    """Subscribe to ``topic`` and spin until ``count`` messages arrive or ``timeout`` s pass; return what came."""
    with MessageCollector(node, {topic: msg_type}, qos) as collector:
        collector.wait_for({topic: count}, timeout)
        return list(collector.messages[topic])
