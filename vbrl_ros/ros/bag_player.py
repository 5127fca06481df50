"""The bag player behind ``vbrl replay``: a bag's topics over ROS 2, paced like the recording.

A stand-in for ``ros2 bag play`` that needs only the pip-installed rclpy. It
reads any bag :class:`~vbrl_ros.datasets.rosbag.RosbagSource` reads (ROS 2
mcap / sqlite3, ROS 1 ``.bag``) lazily, one message at a time, and publishes:

* by default every ``PointCloud2``, ``Odometry``, ``PoseStamped`` and
  ``PoseWithCovarianceStamped`` topic (``--topics`` picks any topics whose
  message package is installed);
* ``/clock`` (``rosgraph_msgs/Clock``) with the bag time: at each message its
  log time, and in between ticks at ``clock_hz`` of wall time, so nodes with
  ``use_sim_time`` see time advance in sync with the data. ``--loop`` makes
  the clock jump back at each new pass, as ``ros2 bag play --loop`` does.

Pacing: message i goes out at ``wall0 + (log_i - log_0) / rate`` on the
monotonic clock. Every wait is towards that absolute target, so sleep
overshoot never accumulates; when publishing falls behind (huge clouds at a
high rate), messages go out back to back until the schedule is caught up.

QoS: cloud, odometry and pose publishers are reliable with keep-all history
by default. Replay exists to evaluate loop closure, so a lost cloud would
silently change the result: a keep-all writer never discards a sample that a
reliable subscriber has not acknowledged (keep-last loses large clouds at
high rates; keep-all does not), and a reliable
publisher still matches subscribers that ask for sensor-data (best-effort)
QoS. ``cloud_qos="sensor"`` makes clouds best-effort like a real driver, to
test a node under loss. The price of keep-all: samples wait in the writer
until acknowledged, so a subscriber that hangs without leaving makes memory
grow until DDS declares it gone. The clock is reliable keep-last 10: only
its newest value matters.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from vbrl_ros.ros.message_conversion import CLOUD_TYPE, MessageTypeError, converter_for, message_class

# Heavy modules (rclpy, rosbags, vbrl_ros.datasets which pulls scipy) are imported where used:
# ``vbrl --help`` imports this module.
DEFAULT_TYPES = (CLOUD_TYPE, "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
                 "geometry_msgs/msg/PoseWithCovarianceStamped")
CLOCK_TOPIC = "/clock"  # remap it like any topic: {"/clock": "/sim_clock"}
QOS_CHOICES = ("reliable", "sensor")
QOS_DEPTH = 10  # the clock's keep-last depth (keep-all ignores it; sensor-data QoS has its own, 5)
FINAL_ACK_TIMEOUT = 0.5  # seconds, at most, to wait for the last samples' acknowledgements


class ReplayError(ValueError):
    """The bag, a topic or an option cannot be replayed as asked (one line, for the CLI)."""


# --------------------------------------------------------------------------- statistics


@dataclass
class ReplayStats:
    """What a replay published; updated live, so it is meaningful after an interruption too."""

    messages: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    passes: int = 0
    bag_seconds: float = 0.0  # bag time covered, summed over passes
    wall_seconds: float = 0.0  # from the first to the last publication

    def summary(self, rate: float) -> str:
        """One line: counts per topic, messages per second and the achieved speed (bag s per wall s)."""
        topics = ", ".join(f"{topic} {count}" for topic, count in sorted(self.per_topic.items())) or "none"
        wall = self.wall_seconds or float("nan")
        return (f"published {self.messages} messages ({topics}) in {self.wall_seconds:.2f} s over {self.passes} "
                f"pass(es): {self.messages / wall:.1f} msg/s, {self.bag_seconds / wall:.2f}x bag time "
                f"(requested {rate:g}x)")


# --------------------------------------------------------------------------- the player


class BagPlayer:
    """Publishes topics of one bag over ROS 2 with the bag's timing; see the module docstring.

    The constructor opens and checks the bag and every option (no DDS yet),
    so mistakes fail fast with a :class:`ReplayError`. :meth:`play` then
    publishes; use the player as a context manager to close the bag.
    """

    def __init__(self, bag: str | Path, *, topics: Sequence[str] | None = None, rate: float = 1.0,
                 start_offset: float = 0.0, duration: float | None = None, loop: bool = False,
                 remaps: dict[str, str] | None = None, cloud_qos: str = "reliable", clock: bool = True,
                 clock_hz: float = 40.0) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        from vbrl_ros.datasets.base import ScanSourceError
        from vbrl_ros.datasets.rosbag import bag_paths

        for ok, problem in [(rate > 0 and math.isfinite(rate), f"rate must be a positive number, got {rate}"),
                            (start_offset >= 0, f"start offset must be >= 0 s, got {start_offset}"),
                            (duration is None or duration > 0, f"duration must be > 0 s, got {duration}"),
                            (cloud_qos in QOS_CHOICES, f"cloud QoS must be one of {QOS_CHOICES}, got {cloud_qos!r}")]:
            if not ok:
                raise ReplayError(problem)
        self.path = Path(bag)
        self.rate, self.loop, self.cloud_qos = float(rate), loop, cloud_qos
        self.clock_topic, self.clock_hz = CLOCK_TOPIC if clock else None, float(clock_hz)
        try:
            paths = bag_paths(self.path)
            self._reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_JAZZY))
            self._reader.open()
        except ScanSourceError as error:
            raise ReplayError(str(error)) from None
        except (AnyReaderError, OSError) as error:
            raise ReplayError(f"{self.path}: cannot open bag: {error}") from None
        self.topics = self._select_topics(topics)
        self.msgtypes = {topic: self._reader.topics[topic].msgtype for topic in self.topics}
        self.outputs = self._resolve_remaps(remaps or {})
        try:
            self._converters = {topic: converter_for(msgtype) for topic, msgtype in self.msgtypes.items()}
        except MessageTypeError as error:
            raise ReplayError(str(error)) from None
        self._connections = [c for c in self._reader.connections if c.topic in self.msgtypes]
        self.start_ns = self._reader.start_time + round(start_offset * 1e9)
        if self.start_ns >= self._reader.end_time:
            raise ReplayError(f"{self.path}: start offset {start_offset:g} s is past the bag's end "
                              f"({self._reader.duration / 1e9:.3f} s long)")
        self.stop_ns = None if duration is None else self.start_ns + round(duration * 1e9)
        self.total = self._count_messages(start_offset > 0 or duration is not None)
        if self.total == 0:
            raise ReplayError(f"{self.path}: no messages on {', '.join(self.topics)} in the chosen time window")
        self.stats = ReplayStats()

    def _select_topics(self, topics: Sequence[str] | None) -> list[str]:
        available = self._reader.topics
        listing = ", ".join(f"{topic} ({info.msgtype})" for topic, info in sorted(available.items())) or "none"
        if topics is None:
            chosen = sorted(topic for topic, info in available.items() if info.msgtype in DEFAULT_TYPES)
            if not any(available[topic].msgtype == CLOUD_TYPE for topic in chosen):
                raise ReplayError(f"{self.path}: no {CLOUD_TYPE} topic in the bag (topics: {listing})")
            return chosen
        if missing := [topic for topic in topics if topic not in available]:
            raise ReplayError(f"{self.path}: no topic {', '.join(missing)} in the bag (topics: {listing})")
        return list(dict.fromkeys(topics))  # keep the order given, drop repeats

    def _resolve_remaps(self, remaps: dict[str, str]) -> dict[str, str]:
        """Bag topic (or the clock topic) -> published name, checked before any DDS entity exists."""
        from rclpy.validate_topic_name import InvalidTopicNameException, validate_topic_name

        known = set(self.topics) | ({self.clock_topic} if self.clock_topic else set())
        if unknown := sorted(set(remaps) - known):
            raise ReplayError(f"cannot remap {', '.join(unknown)}: not a replayed topic ({', '.join(sorted(known))})")
        outputs = {topic: remaps.get(topic, topic) for topic in known}
        for name in outputs.values():
            try:
                validate_topic_name(name)
            except InvalidTopicNameException as error:
                reason = str(error).splitlines()[0].removeprefix("Invalid topic name: ").rstrip(":")
                raise ReplayError(f"invalid topic name {name!r}: {reason}") from None
        types: dict[str, str] = {}
        for topic in self.topics:  # two bag topics may merge into one name only if their types agree
            if types.setdefault(outputs[topic], self.msgtypes[topic]) != self.msgtypes[topic]:
                raise ReplayError(f"remaps publish two message types on {outputs[topic]}")
        if self.clock_topic and outputs[self.clock_topic] in types:
            raise ReplayError(f"the clock topic {outputs[self.clock_topic]} is also a replayed topic")
        return outputs

    def _count_messages(self, windowed: bool) -> int:
        if not windowed:
            return sum(self._reader.topics[topic].msgcount for topic in self.topics)
        # One pass over the window's raw bytes (nothing is deserialised) for an exact progress total.
        return sum(1 for _ in self._reader.messages(self._connections, start=self.start_ns, stop=self.stop_ns))

    # ------------------------------------------------------------------- playing

    def play(self, context: Any = None, *, delay: float = 0.0, wait_for_subscribers: int = 0,
             wait_topics: Sequence[str] | None = None, wait_timeout: float = 30.0, progress: bool | None = False,
             stop: threading.Event | None = None) -> ReplayStats:
        """Publish the bag (once, or until ``stop`` is set / Ctrl-C with ``loop``); return the statistics.

        ``context``: an initialised rclpy Context; by default a private one is
        made on ``ROS_DOMAIN_ID`` and shut down at the end. Before the first
        message, waits until each of ``wait_topics`` (published names; default
        every replayed topic, not the clock) has ``wait_for_subscribers``
        subscribers (ReplayError after ``wait_timeout`` s), then ``delay`` s.
        ``progress``: tqdm bar (None: only on a terminal).
        """
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        stop = stop or threading.Event()
        self.stats, self._first_wall = ReplayStats(), 0.0
        own_context = context is None
        if own_context:
            context = rclpy.Context()
            # Without rclpy's own handlers, Ctrl-C is a plain KeyboardInterrupt and we tear down in order.
            rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        node = None
        try:
            node = rclpy.create_node("vbrl_replay", context=context)
            publishers, clock = self._publishers(node)
            self._warm_up()
            self._wait_for_subscribers(publishers, wait_for_subscribers, wait_topics, wait_timeout, stop)
            if delay > 0:
                stop.wait(delay)
            self._play_passes(publishers, clock, progress, stop)
            self._let_subscribers_acknowledge(publishers)
        finally:
            if node is not None:
                node.destroy_node()
            if own_context:
                context.try_shutdown()
        return self.stats

    def _publishers(self, node: Any) -> tuple[dict[str, Any], Any]:
        """(publisher of every replayed topic, the clock's publisher or None)."""
        from rclpy.qos import HistoryPolicy, QoSProfile, qos_profile_sensor_data

        # Keep-all: the writer never discards a sample a reliable subscriber has not acknowledged.
        reliable = QoSProfile(depth=QOS_DEPTH, history=HistoryPolicy.KEEP_ALL)
        publishers = {}
        for topic in self.topics:
            sensor = self.cloud_qos == "sensor" and self.msgtypes[topic] == CLOUD_TYPE
            publishers[topic] = node.create_publisher(message_class(self.msgtypes[topic]), self.outputs[topic],
                                                      qos_profile_sensor_data if sensor else reliable)
        clock = None
        if self.clock_topic:
            from rosgraph_msgs.msg import Clock

            clock = node.create_publisher(Clock, self.outputs[self.clock_topic], QoSProfile(depth=QOS_DEPTH))
        return publishers, clock

    def _play_passes(self, publishers: dict[str, Any], clock: Any, progress: bool | None,
                     stop: threading.Event) -> None:
        """One pass, or passes until ``stop`` with ``loop``, under one progress bar."""
        from tqdm import tqdm

        with tqdm(total=self.total, desc=f"replay {self.path.name}", unit="msg", dynamic_ncols=True,
                  disable=None if progress is None else not progress) as bar:
            while not stop.is_set():
                self.stats.passes += 1
                bar.reset(total=self.total)
                if self.loop:
                    bar.set_description(f"replay {self.path.name} pass {self.stats.passes}")
                self._play_pass(publishers, clock, bar, stop)
                if not self.loop:
                    break

    @staticmethod
    def _let_subscribers_acknowledge(publishers: dict[str, Any]) -> None:
        """Give subscribers a moment to acknowledge the last samples (a retransmission needs the writer
        alive). Bounded: Fast DDS readers ack only on the writer's heartbeat, which comes at once after
        large samples but up to ~3 s later after small ones, and nobody wants replay to hang that long."""
        from rclpy.duration import Duration
        from rclpy.qos import ReliabilityPolicy

        deadline = time.monotonic() + FINAL_ACK_TIMEOUT
        for publisher in publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=max(0.0, deadline - time.monotonic())))
        if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers.values()):
            # A best-effort writer is never acknowledged, so the wait above returns at once, and
            # destroying it right away could lose the last large (fragmented) sample.
            time.sleep(max(0.0, deadline - time.monotonic()))

    def _warm_up(self) -> None:
        """Convert one message per topic: rosbags compiles its deserialisers on first use (~10 ms each)."""
        for connection in {c.topic: c for c in self._connections}.values():
            for _, _, rawdata in self._reader.messages([connection], start=self.start_ns, stop=self.stop_ns):
                self._converters[connection.topic](self._reader.deserialize(rawdata, connection.msgtype))
                break

    def _wait_for_subscribers(self, publishers: dict[str, Any], count: int, wait_topics: Sequence[str] | None,
                              timeout: float, stop: threading.Event) -> None:
        if count <= 0:
            return
        by_output = {self.outputs[topic]: publisher for topic, publisher in publishers.items()}
        names = list(wait_topics) if wait_topics else list(by_output)
        if unknown := [name for name in names if name not in by_output]:
            raise ReplayError(f"cannot wait on {', '.join(unknown)}: not a published topic ({', '.join(by_output)})")
        deadline = time.monotonic() + timeout
        while not stop.is_set():  # matching happens in DDS threads: no spinning needed, only polling
            short = [name for name in names if by_output[name].get_subscription_count() < count]
            if not short:
                return
            if time.monotonic() > deadline:
                raise ReplayError(f"timed out after {timeout:g} s waiting for {count} subscriber(s) on "
                                  f"{', '.join(short)}")
            stop.wait(0.02)

    def _play_pass(self, publishers: dict[str, Any], clock: Any, bar: Any, stop: threading.Event) -> None:
        from builtin_interfaces.msg import Time
        from rosgraph_msgs.msg import Clock

        last_clock = -1

        def publish_clock(bag_ns: int) -> None:
            nonlocal last_clock
            if clock is not None and bag_ns != last_clock:  # messages sharing a log time share one tick
                clock.publish(Clock(clock=Time(sec=bag_ns // 1_000_000_000, nanosec=bag_ns % 1_000_000_000)))
                last_clock = bag_ns

        wall0 = log0 = last_log = None  # set by the pass's first message
        period = 1.0 / self.clock_hz if self.clock_hz > 0 and clock is not None else float("inf")
        next_tick = 0.0
        for connection, log_ns, rawdata in self._reader.messages(self._connections, start=self.start_ns,
                                                                  stop=self.stop_ns):
            # Decode before waiting, so the conversion cost never delays the publication.
            try:
                msg = self._converters[connection.topic](self._reader.deserialize(rawdata, connection.msgtype))
            except Exception as error:  # rosbags' errors on corrupt bytes, rclpy's on out-of-range values
                raise ReplayError(f"{self.path} {connection.topic} at {log_ns} ns: cannot convert: {error}") from None
            if wall0 is None:
                wall0, log0, last_log = time.monotonic(), log_ns, log_ns
                next_tick = wall0 + period
                self._first_wall = self._first_wall or wall0
            target = wall0 + (log_ns - log0) / 1e9 / self.rate
            while (now := time.monotonic()) < target:
                if next_tick < target:  # a clock tick falls before this message: sleep to it, publish it
                    if stop.wait(max(0.0, next_tick - now)):
                        return
                    publish_clock(min(log_ns, log0 + round((next_tick - wall0) * self.rate * 1e9)))
                    next_tick = max(next_tick + period, time.monotonic())  # no tick bursts after a stall
                elif stop.wait(target - now):
                    return
            if stop.is_set():
                return
            publish_clock(log_ns)  # before the message: a sim-time node never sees data from its future
            publishers[connection.topic].publish(msg)
            self.stats.messages += 1
            self.stats.per_topic[connection.topic] = self.stats.per_topic.get(connection.topic, 0) + 1
            self.stats.bag_seconds += (log_ns - last_log) / 1e9
            self.stats.wall_seconds, last_log = time.monotonic() - self._first_wall, log_ns
            bar.update()

    # ------------------------------------------------------------------- lifetime

    def close(self) -> None:
        """Close the bag (idempotent)."""
        reader = getattr(self, "_reader", None)
        if reader is not None and reader.stack is not None:
            reader.close()

    def __enter__(self) -> BagPlayer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
