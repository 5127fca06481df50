"""A short queue between two threads in which, when it is full, the newest item wins.

The node hands keyframes to its worker, and retrievals to its verification
thread, through one each: a producer never waits; when the consumer has fallen
``capacity`` items behind, the oldest waiting item is dropped for the new one
and the caller counts it. A few places absorb a short stall of the consumer (a
database save holds the worker for a few hundred milliseconds); under sustained
overload the consumer works on recent items and nothing grows.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class NewestQueue(Generic[T]):
    def __init__(self, capacity: int = 1) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._condition = threading.Condition()
        self._items: deque[T] = deque()
        self._capacity = capacity
        self._closed = False

    def put(self, item: T) -> bool:
        """Queue ``item``; True when the oldest waiting item was dropped to make room."""
        with self._condition:
            dropped = len(self._items) >= self._capacity
            if dropped:
                self._items.popleft()
            self._items.append(item)
            self._condition.notify()
            return dropped

    def take(self, timeout: float | None = None) -> T | None:
        """The oldest waiting item (blocks until there is one); None once closed, even if some wait.
        Raises TimeoutError when ``timeout`` seconds (None: no limit) pass without one."""
        with self._condition:
            if not self._condition.wait_for(lambda: self._items or self._closed, timeout):
                raise TimeoutError(f"nothing came within {timeout:g} s")
            if self._closed:
                return None
            return self._items.popleft()

    def close(self) -> None:
        """Wake the consumer for good: every later :meth:`take` returns None."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()
