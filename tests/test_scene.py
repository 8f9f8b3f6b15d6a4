"""app/server/scene.py's wake-up of viser's senders from this server's thread."""

from __future__ import annotations

import asyncio
import threading
import time

from app.server.scene import LoopSafeEvent
from harness import running_server


def test_a_loop_safe_event_set_from_another_thread_wakes_its_loop():
    """viser's loop waits and clears in its thread while ours sets the event as fast as
    it can: every round is woken, and a set never runs the waiters in our thread."""
    loop = asyncio.new_event_loop()
    th = threading.Thread(target=loop.run_forever, daemon=True)
    th.start()
    ev = LoopSafeEvent(loop)
    rounds = 2000

    async def sender():           # viser's window generator, reduced to its wait
        for _ in range(rounds):
            await ev.wait()
            ev.clear()

    done = asyncio.run_coroutine_threadsafe(sender(), loop)
    deadline = time.monotonic() + 60.0
    try:
        while not done.done() and time.monotonic() < deadline:
            ev.set()              # from this thread: handed to the loop
        assert done.result(timeout=1.0) is None, "the waiter was not woken every round"
    finally:
        loop.call_soon_threadsafe(loop.stop)
        th.join(5.0)
    # set in its own loop: at once, as asyncio.Event does
    loop2 = asyncio.new_event_loop()
    ev2 = LoopSafeEvent(loop2)

    async def own():
        ev2.set()
        return ev2.is_set()

    assert loop2.run_until_complete(own()) is True
    loop2.close()
    ev3 = LoopSafeEvent(loop2)    # a closed loop: a set is dropped, no error
    ev3.set()
    assert not ev3.is_set()


def test_the_servers_viewer_wakes_its_senders_the_loop_safe_way():
    with running_server() as srv:
        buf = srv.app.state.viewer._websock_server._broadcast_buffer
        assert isinstance(buf.message_event, LoopSafeEvent)
