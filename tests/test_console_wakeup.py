"""viser's message events, set from the console's job threads while the loop waits on them
(``app.console.wakeup``): a job thread never walks the waiters the loop is adding to, and the
loop's own set still wakes every waiter."""

from __future__ import annotations

import asyncio
import threading

from viser.infra._async_message_buffer import AsyncMessageBuffer

from probecal.app.console import wakeup
from probecal.app.console.server import launch


def test_a_thread_raises_the_flag_and_the_loop_wakes_the_waiters():
    async def scenario() -> list[bool]:
        event = wakeup.ThreadTolerantEvent()
        waiters = [asyncio.ensure_future(event.wait()) for _ in range(3)]
        await asyncio.sleep(0)  # every waiter is now in the event's deque
        before = list(event._waiters)
        thread = threading.Thread(target=event.set)
        thread.start()
        thread.join()
        flagged = event.is_set() and list(event._waiters) == before and not any(w.done() for w in waiters)
        asyncio.get_running_loop().call_soon_threadsafe(event.set)  # what viser schedules with it
        done, _ = await asyncio.wait(waiters, timeout=5.0)
        return [flagged, len(done) == len(waiters)]

    assert asyncio.run(scenario()) == [True, True]


def test_the_console_s_message_buffers_take_the_tolerant_events(tmp_path):
    console = launch(port=0, sessions_dir=tmp_path)
    try:
        loop = asyncio.new_event_loop()
        buffer = AsyncMessageBuffer(loop, persistent_messages=True)
        assert isinstance(buffer.message_event, wakeup.ThreadTolerantEvent)
        assert isinstance(buffer.flush_event, wakeup.ThreadTolerantEvent)
        loop.close()
    finally:
        console.close()
