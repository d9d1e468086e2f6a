"""Bounded hand-off from a transport thread (Zenoh callbacks, a MAVLink reader) to asyncio."""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class ThreadToAsyncRing(Generic[T]):
    """A bounded ring filled from any thread and drained by one asyncio consumer.

    :meth:`put` never blocks the producer: when the ring is full the *oldest*
    items are dropped and counted in :attr:`dropped`. ``capacity`` and
    :attr:`dropped` are in units of ``weight(item)`` (default: items; a
    source of batches passes their sample count). The consumer is woken
    through ``loop.call_soon_threadsafe``, once per empty → non-empty
    transition rather than once per item, so a burst costs one wake-up.
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
        self._capacity = int(capacity)
        self._loop = loop
        self._weight = weight
        self._held = 0
        self._items: deque[tuple[T, int]] = deque()
        self._lock = threading.Lock()
        self._wake = asyncio.Event()
        self._wake_pending = False
        self._closed = False
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
            if self._wake_pending:
                return
            self._wake_pending = True
        self._notify()

    def _drop_oldest(self) -> None:
        w = self._items.popleft()[1]
        self._held -= w
        self.dropped += w

    def _pop(self) -> T:
        item, w = self._items.popleft()
        self._held -= w
        return item

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
                if self._items:
                    return self._pop()
                self._wake_pending = False
                self._wake.clear()
                closed = self._closed
            if closed:
                raise EOFError("the source is closed")
            await self._wake.wait()

    def get_nowait(self) -> T | None:
        """The next item, or ``None`` if the ring is empty."""
        with self._lock:
            return self._pop() if self._items else None

    def close(self) -> None:
        """Stop accepting items; a waiting consumer drains what is left, then gets ``EOFError``."""
        with self._lock:
            self._closed = True
        self._notify()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
