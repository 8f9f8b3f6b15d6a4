"""Heavy jobs one at a time per kind (issue 21, item 9) and a calibration's collection
bounded whatever the phone's clock does (item 1)."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from app.toolkit import capture as cp
from app.toolkit.errors import ToolError
from app.toolkit.jobs import JobQueue


def test_one_job_at_a_time_two_waiting_the_rest_refused():
    q = JobQueue("test job")
    live, peak, lock = [0], [0], threading.Lock()

    def job(i):
        with lock:
            live[0] += 1
            peak[0] = max(peak[0], live[0])
        time.sleep(0.2)
        with lock:
            live[0] -= 1
        return i

    async def main():
        tasks = [asyncio.ensure_future(q.run(lambda i=i: job(i))) for i in range(6)]
        # the event loop is never blocked: it ticks while the jobs run
        ticks = 0
        while not all(t.done() for t in tasks):
            await asyncio.sleep(0.01)
            ticks += 1
        assert ticks > 0.6 / 0.01 * 0.5, ticks
        return [t.result() if not t.exception() else t.exception() for t in tasks]

    out = asyncio.run(main())
    assert out[:3] == [0, 1, 2]
    for e in out[3:]:
        assert isinstance(e, ToolError) and e.status == 429 and "busy" in e.reason
    assert peak[0] == 1 and q.running == 0 and q.waiting == 0 and q.refused == 3


def test_a_failing_job_frees_its_slot_and_a_cancelled_waiter_leaves():
    q = JobQueue("test job")

    async def main():
        def boom():
            raise ValueError("bad file")
        with pytest.raises(ValueError, match="bad file"):
            await q.run(boom)
        slow = asyncio.ensure_future(q.run(lambda: time.sleep(0.3) or "slow"))
        await asyncio.sleep(0.05)
        waiter = asyncio.ensure_future(q.run(lambda: "never"))
        await asyncio.sleep(0.05)
        assert q.waiting == 1
        waiter.cancel()
        await asyncio.sleep(0)
        assert q.waiting == 0
        assert await slow == "slow"
        assert await q.run(lambda: "next") == "next"
        assert q.running == 0

    asyncio.run(main())


def test_a_frozen_clock_collection_is_capped_in_rows_and_refused():
    cap = cp.Capture("still", 2.0)
    kind = np.zeros(5000, dtype=np.int64)
    vals = np.zeros((5000, 4))
    done = False
    for _ in range(40):                      # 200,000 rows, all at one time stamp
        done = cap.add(np.full(5000, 123.0), kind, vals)
        if done:
            break
    assert done and cap.rows == cp.MAX_ROWS
    assert "cap of 60000 samples" in cap.note
    assert "frozen" in cap.clock_untrusted()


def test_the_wall_time_caps_a_collection():
    cap = cp.Capture("still", 1.0)
    cap.started_wall -= 1.0 + cp.WALL_GRACE_S + 0.1      # as if 6.1 s went by
    cap.add(np.array([5.0, 5.0]), np.zeros(2, dtype=np.int64), np.zeros((2, 4)))
    assert cap.note and "stopped after" in cap.note
    assert cap.check_stalled() and "frozen" in cap.clock_untrusted()
    empty = cp.Capture("still", 1.0)
    empty.started_wall -= 10.0
    assert empty.check_stalled() and "no stream" in empty.error


def test_a_stream_that_stopped_is_told_apart_from_a_frozen_clock():
    cap = cp.Capture("still", 10.0)
    cap.add(np.array([1.0, 2.0]), np.zeros(2, dtype=np.int64), np.zeros((2, 4)))
    cap.started_wall -= 20.0
    cap.last_wall -= 5.0                      # the last sample came 5 s ago
    assert cap.check_stalled() and "stopped streaming" in cap.clock_untrusted()
