"""viser's message buffers, safe to write from the console's job threads.

A sweep, a calibration or a reconstruction runs in a background thread and updates the page as it
goes. viser's ``AsyncMessageBuffer.push`` then calls ``message_event.set()`` on an
``asyncio.Event`` from that thread, besides scheduling the same call on the event loop.
``asyncio.Event.set`` walks the event's waiters, a deque the loop appends to whenever a client's
sender starts to wait; with a few tabs open the walk sometimes meets an append, and the job dies of
``RuntimeError: deque mutated during iteration``. :class:`ThreadTolerantEvent` only raises the
flag when set from another thread (which synchronous readers see at once) and leaves the waking to
the loop's own call, which wakes every waiter whether or not the flag was up already.
"""

from __future__ import annotations

import asyncio
import functools

from viser.infra._async_message_buffer import AsyncMessageBuffer


class ThreadTolerantEvent(asyncio.Event):
    """An ``asyncio.Event`` that may be set from any thread; its waiters wake when the loop sets it."""

    def set(self) -> None:
        try:
            asyncio.get_running_loop()
        except RuntimeError:  # another thread: the flag only; the loop's call (scheduled too) wakes
            self._value = True
            return
        self._value = True
        for waiter in self._waiters:
            if not waiter.done():
                waiter.set_result(True)


def install() -> None:
    """Give every viser message buffer made from now on thread-tolerant events (once)."""
    if getattr(AsyncMessageBuffer.__init__, "thread_tolerant", False):
        return
    original = AsyncMessageBuffer.__init__

    @functools.wraps(original)
    def init(self: AsyncMessageBuffer, *args, **kwargs) -> None:
        original(self, *args, **kwargs)
        self.message_event = ThreadTolerantEvent()
        self.flush_event = ThreadTolerantEvent()

    init.thread_tolerant = True  # type: ignore[attr-defined]
    AsyncMessageBuffer.__init__ = init  # type: ignore[method-assign]
