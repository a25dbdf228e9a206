"""The queue between the capture thread and the event loop: bounded, newest-wins for a live source."""

from __future__ import annotations

import asyncio
import collections
from typing import Generic, TypeVar

T = TypeVar("T")


class FrameQueue(Generic[T]):
    """A bounded FIFO for one producer and one consumer on the event loop's thread.

    ``put_newest`` never waits: when full it drops the oldest item and counts it in :attr:`dropped`
    (the live policy). ``put`` waits for room (the recording policy). ``finish`` says no more items
    will come: ``get`` then returns what is left and ``None`` after it. Not thread-safe: a thread hands
    items over with ``loop.call_soon_threadsafe`` / ``asyncio.run_coroutine_threadsafe``.
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be at least 1, got {maxsize}")
        self.maxsize = maxsize
        self.dropped = 0
        self._items: collections.deque[T] = collections.deque()
        self._finished = False
        self._not_empty = asyncio.Event()
        self._not_full = asyncio.Event()
        self._not_full.set()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def finished(self) -> bool:
        """Whether :meth:`finish` was called."""
        return self._finished

    def put_newest(self, item: T) -> T | None:
        """Add ``item``; if the queue was full, drop and return the oldest item (counted). After
        :meth:`finish`, ``item`` itself is discarded (not counted) and returned."""
        if self._finished:
            return item
        dropped: T | None = None
        if len(self._items) >= self.maxsize:
            dropped = self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._not_empty.set()
        self._update_full()
        return dropped

    async def put(self, item: T) -> bool:
        """Add ``item`` once there is room; ``False`` (and ``item`` discarded) if the queue was finished."""
        while len(self._items) >= self.maxsize and not self._finished:
            await self._not_full.wait()
        if self._finished:
            return False
        self._items.append(item)
        self._not_empty.set()
        self._update_full()
        return True

    async def get(self) -> T | None:
        """The oldest item, waiting for one; ``None`` once the queue is finished and empty."""
        while not self._items:
            if self._finished:
                return None
            self._not_empty.clear()
            await self._not_empty.wait()
        item = self._items.popleft()
        self._update_full()
        if not self._items and not self._finished:
            self._not_empty.clear()
        return item

    def take_all(self) -> list[T]:
        """Every item queued now, oldest first, without waiting (a live source's run of frames)."""
        items = list(self._items)
        self._items.clear()
        self._update_full()
        if not self._finished:
            self._not_empty.clear()
        return items

    def finish(self, discard: bool = False) -> int:
        """No more items will be put; wakes every waiter. With ``discard``, drops what is queued (not
        counted in :attr:`dropped`) and returns how many."""
        self._finished = True
        count = 0
        if discard:
            count = len(self._items)
            self._items.clear()
        self._not_empty.set()
        self._not_full.set()
        return count

    def _update_full(self) -> None:
        if len(self._items) >= self.maxsize:
            self._not_full.clear()
        else:
            self._not_full.set()
