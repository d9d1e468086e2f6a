"""Bounded hand-off from a transport thread (Zenoh callbacks, a MAVLink reader) to asyncio."""

from __future__ import annotations

import asyncio
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
K = TypeVar("K")


class _Handoff(ABC, Generic[T]):
    """What both hand-offs share: one lock, the consumer woken through ``loop.call_soon_threadsafe``
    once per empty → non-empty transition rather than once per item (a burst costs one wake-up),
    :meth:`get`/:meth:`get_nowait` over the subclass's :meth:`_pop`, and closing."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self._loop = loop
        self._lock = threading.Lock()
        self._wake = asyncio.Event()
        self._wake_pending = False
        self._closed = False

    @abstractmethod
    def _has_items(self) -> bool:
        """Under the lock: whether an item waits."""

    @abstractmethod
    def _pop(self) -> T:
        """Under the lock, with an item waiting: the next one."""

    def _wake_needed(self) -> bool:
        """Under the lock, after an item was added: whether the consumer must be woken (:meth:`_notify`)."""
        if self._wake_pending:
            return False
        self._wake_pending = True
        return True

    def _notify(self) -> None:
        try:
            self._loop.call_soon_threadsafe(self._wake.set)
        except RuntimeError:
            # The loop is closed: the consumer is gone, so is the need to wake it.
            with self._lock:
                self._closed = True

    async def get(self) -> T:
        """The next item; waits while empty; raises ``EOFError`` once closed and drained."""
        while True:
            with self._lock:
                if self._has_items():
                    return self._pop()
                self._wake_pending = False
                self._wake.clear()
                closed = self._closed
            if closed:
                raise EOFError("the source is closed")
            await self._wake.wait()

    def get_nowait(self) -> T | None:
        """The next item, or ``None`` if nothing waits."""
        with self._lock:
            return self._pop() if self._has_items() else None

    def close(self) -> None:
        """Stop accepting items; a waiting consumer drains what is left, then gets ``EOFError``."""
        with self._lock:
            self._closed = True
        self._notify()

    @property
    def closed(self) -> bool:
        return self._closed


class ThreadToAsyncRing(_Handoff[T]):
    """A bounded ring filled from any thread and drained by one asyncio consumer.

    :meth:`put` never blocks the producer: when the ring is full the *oldest*
    items are dropped and counted in :attr:`dropped`. ``capacity`` and
    :attr:`dropped` are in units of ``weight(item)`` (default: items; a
    source of batches passes their sample count).
    """

    def __init__(
        self,
        capacity: int,
        loop: asyncio.AbstractEventLoop,
        *,
        weight: Callable[[T], int] | None = None,
    ):
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        super().__init__(loop)
        self._capacity = int(capacity)
        self._weight = weight
        self._held = 0
        self._items: deque[tuple[T, int]] = deque()
        self.put_count = 0
        self.dropped = 0

    def put(self, item: T) -> None:
        """Add an item from any thread (dropping the oldest when full); ignored once closed."""
        with self._lock:
            if self._closed:
                return
            self.put_count += 1
            w = 1 if self._weight is None else self._weight(item)
            while self._items and self._held + w > self._capacity:
                self._drop_oldest()
            self._items.append((item, w))
            self._held += w
            if not self._wake_needed():
                return
        self._notify()

    def _drop_oldest(self) -> None:
        w = self._items.popleft()[1]
        self._held -= w
        self.dropped += w

    def _has_items(self) -> bool:
        return bool(self._items)

    def _pop(self) -> T:
        item, w = self._items.popleft()
        self._held -= w
        return item

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)


class FairQueues(_Handoff[T], Generic[K, T]):
    """One bounded queue per key (a (vehicle, IMU)), filled from any thread and drained by one asyncio
    consumer in turn, so that a key that floods costs no other key its items.

    Drop policy (the newest is dropped, the queued items keep their order and their stream no
    hole but the one at its end):

    * a key's queue holds at most ``capacity`` items; one more is dropped;
    * all queues together hold at most ``total``: when full, a key holding less than its fair share
      (``total`` over the keys holding items, this one included) takes the place of the newest item
      of the longest queue, and one holding its share or more has its new item dropped.

    Every drop is counted against the key whose item it was (:attr:`dropped`, :attr:`received`).
    :meth:`get` takes the keys in turn, one item each, the oldest of each key's queue.
    """

    def __init__(self, capacity: int, total: int, loop: asyncio.AbstractEventLoop):
        if capacity < 1 or total < 1:
            raise ValueError(f"capacities must be >= 1, got {capacity} and {total}")
        super().__init__(loop)
        self._capacity, self._total = int(capacity), int(total)
        self._queues: dict[K, deque[T]] = {}
        self._turn: deque[K] = deque()
        self._held = 0
        self.received: dict[K, int] = {}
        self.dropped: dict[K, int] = {}

    def put(self, key: K, item: T) -> None:
        """Add ``key``'s item from any thread (or drop and count it, class docstring); ignored once closed."""
        with self._lock:
            if self._closed:
                return
            self.received[key] = self.received.get(key, 0) + 1
            queue = self._queues.get(key)
            held = 0 if queue is None else len(queue)
            if held >= self._capacity:
                self._drop(key)
                return
            if self._held >= self._total:
                keys = len(self._queues) + (queue is None)
                longest = max(self._queues, key=lambda k: len(self._queues[k]))
                if held >= self._total // keys or longest == key:
                    self._drop(key)
                    return
                self._queues[longest].pop()
                self._drop(longest)
                self._held -= 1
                if not self._queues[longest]:
                    del self._queues[longest]
                    self._turn.remove(longest)
            if queue is None:
                queue = self._queues[key] = deque()
                self._turn.append(key)
            queue.append(item)
            self._held += 1
            if not self._wake_needed():
                return
        self._notify()

    def _drop(self, key: K) -> None:
        self.dropped[key] = self.dropped.get(key, 0) + 1

    def _pop(self) -> T:
        key = self._turn.popleft()
        queue = self._queues[key]
        item = queue.popleft()
        self._held -= 1
        if queue:
            self._turn.append(key)
        else:
            del self._queues[key]
        return item

    def _has_items(self) -> bool:
        return bool(self._turn)

    def counts(self) -> tuple[dict[K, int], dict[K, int]]:
        """Snapshots of :attr:`received` and :attr:`dropped` (the producer's thread adds keys)."""
        with self._lock:
            return dict(self.received), dict(self.dropped)

    def queued(self, key: K) -> int:
        """Items of ``key`` waiting."""
        with self._lock:
            queue = self._queues.get(key)
            return 0 if queue is None else len(queue)

    def __len__(self) -> int:
        with self._lock:
            return self._held
