"""The node's counters and recent timings, shared by its threads behind one lock.

The executor thread (subscriptions, services, the diagnostics timer) and the
worker thread both write here, and the timer reads everything at once: every
access goes through :class:`NodeStats`' methods, which hold its lock, and the
timer reads a consistent :meth:`NodeStats.snapshot`.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field, fields

import numpy as np

RATE_WINDOW_S = 5.0


@dataclass(frozen=True)
class StatsSnapshot:
    """The counters at one instant, and the timings derived from that instant's samples."""

    scans: int = 0
    lost: int = 0  # published, but never reached the node (its DDS queue overflowed, or the transport)
    between_keyframes: int = 0  # valid or not, too close to the last keyframe to be one
    keyframes: int = 0  # described, searched and stored
    closures: int = 0
    corroborated: int = 0  # of the closures, accepted below min_fitness as the keyframes before agreed
    handed_on: int = 0  # of the closures, published to a stored keyframe nearer the query than the one registered
    rejected_by_verification: int = 0
    dropped: int = 0  # keyframes replaced by a newer one before the worker took them
    unverified: int = 0  # keyframes whose candidates a newer keyframe's replaced before verification
    verification_errors: int = 0
    malformed: int = 0
    empty: int = 0
    errors: int = 0
    failed_saves: int = 0
    odometry: int = 0
    bad_odometry: int = 0
    late_odometry: int = 0  # keyframes stored with the newest pose: odometry had not reached their stamp
    input_rate_hz: float = 0.0
    # p50, p90, p99 from a cloud's arrival until its closures are decided (verified or not) ...
    latency_ms: tuple[float, float, float] = (float("nan"),) * 3
    # ... and until it is described, searched and stored
    retrieval_latency_ms: tuple[float, float, float] = (float("nan"),) * 3

    @property
    def problems(self) -> int:
        """Scans, odometry or saves lost to a fault or to the node's slowness."""
        return (self.lost + self.malformed + self.empty + self.errors + self.dropped + self.unverified
                + self.verification_errors + self.bad_odometry + self.failed_saves)


#: The counters (every int field of :class:`StatsSnapshot`).
COUNTERS = tuple(f.name for f in fields(StatsSnapshot) if f.type in ("int", int))


@dataclass
class NodeStats:
    """Counters and recent arrival times and latencies; safe to use from any thread."""

    _counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTERS, 0))
    _arrivals: deque = field(default_factory=lambda: deque(maxlen=2000))
    _latencies_ms: deque = field(default_factory=lambda: deque(maxlen=1000))
    _retrieval_latencies_ms: deque = field(default_factory=lambda: deque(maxlen=1000))
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def received(self, now: float) -> None:
        with self._lock:
            self._counts["scans"] += 1
            self._arrivals.append(now)

    def keyframe(self, latency_ms: float) -> None:
        """A keyframe described, searched and stored ``latency_ms`` after its cloud arrived."""
        with self._lock:
            self._counts["keyframes"] += 1
            self._retrieval_latencies_ms.append(latency_ms)

    def decided(self, latency_ms: float, closures: int, rejected_by_verification: int,
                corroborated: int = 0, handed_on: int = 0) -> None:
        """A keyframe's closures decided ``latency_ms`` after its cloud arrived (``corroborated`` of them,
        ``handed_on`` to a nearer keyframe)."""
        with self._lock:
            self._counts["closures"] += closures
            self._counts["corroborated"] += corroborated
            self._counts["handed_on"] += handed_on
            self._counts["rejected_by_verification"] += rejected_by_verification
            self._latencies_ms.append(latency_ms)

    def snapshot(self, now: float | None = None) -> StatsSnapshot:
        now = time.monotonic() if now is None else now
        with self._lock:
            counts = dict(self._counts)
            arrivals = np.array(self._arrivals)
            latencies = np.array(self._latencies_ms)
            retrieval = np.array(self._retrieval_latencies_ms)
        rate = float(np.count_nonzero(now - arrivals <= RATE_WINDOW_S)) / RATE_WINDOW_S
        return StatsSnapshot(**counts, input_rate_hz=rate, latency_ms=percentiles(latencies),
                             retrieval_latency_ms=percentiles(retrieval))


def percentiles(values: np.ndarray) -> tuple[float, float, float]:
    """p50, p90, p99 (NaN without values)."""
    if len(values) == 0:
        return (float("nan"),) * 3
    p50, p90, p99 = np.percentile(values, [50, 90, 99])
    return float(p50), float(p90), float(p99)
