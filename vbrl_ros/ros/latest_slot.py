"""A one-item mailbox between two threads in which the newest item wins.

The node hands keyframes to its worker, and retrievals to its verification
thread, through one each: a producer never waits, a consumer that falls behind
skips to the newest item, and the caller counts what was replaced. Nothing
queues, so nothing grows.
"""

from __future__ import annotations

import threading
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: T | None = None
        self._closed = False

    def put(self, item: T) -> bool:
        """Leave ``item`` for the consumer; True when it replaced one that was still waiting."""
        with self._condition:
            replaced = self._item is not None
            self._item = item
            self._condition.notify()
            return replaced

    def take(self) -> T | None:
        """The waiting item (blocks until there is one); None once closed, even if one waits."""
        with self._condition:
            while self._item is None and not self._closed:
                self._condition.wait()
            if self._closed:
                return None
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        """Wake the consumer for good: every later :meth:`take` returns None."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()
