"""The node's hand-over queues: bounded, oldest dropped first, a blocked consumer woken by close."""

from __future__ import annotations

import threading

import pytest

from vbrl_ros.ros.newest_queue import NewestQueue


def test_a_full_queue_drops_the_oldest_and_keeps_the_newest_in_order():
    queue: NewestQueue[int] = NewestQueue(3)
    assert [queue.put(k) for k in range(5)] == [False, False, False, True, True]
    assert [queue.take() for _ in range(3)] == [2, 3, 4]


def test_close_wakes_a_waiting_consumer_and_ends_taking():
    queue: NewestQueue[int] = NewestQueue(1)
    taken = []
    consumer = threading.Thread(target=lambda: taken.append(queue.take()))
    consumer.start()
    queue.close()
    consumer.join(timeout=5)
    assert not consumer.is_alive() and taken == [None]
    queue.put(1)
    assert queue.take() is None


def test_capacity_must_be_positive():
    with pytest.raises(ValueError, match="capacity"):
        NewestQueue(0)


def test_a_take_with_a_timeout_raises_when_nothing_comes_and_returns_what_does():
    queue = NewestQueue(2)
    with pytest.raises(TimeoutError, match="nothing came within 0.05 s"):
        queue.take(timeout=0.05)
    queue.put(7)
    assert queue.take(timeout=0.05) == 7
    queue.close()
    assert queue.take(timeout=0.05) is None  # closed is not a timeout
