"""Heavy jobs, one at a time per kind: a what-if re-run or a calibration of a long
recording costs seconds of CPU. Run in an unbounded pool, eight at once froze the API
(``/api/health`` answered 3 of 7 polls, the slowest in 3.7 s): every thread competes with
the event loop for the interpreter.

A :class:`JobQueue` runs its kind's jobs in a worker thread, ``workers`` (1) at a time;
up to ``waiting`` (2) more wait their turn in order; one more is refused at once with a
:class:`~app.toolkit.errors.ToolError` (429, "busy", saying what runs and waits). The
event loop only awaits a future: it never blocks on a job. A job whose caller went away
(a closed connection) still holds its slot until its thread ends, so there is never more
than ``workers`` running.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from typing import Any, Callable

from app.toolkit.errors import ToolError

WORKERS = 1
WAITING = 2


class JobQueue:
    """One kind of heavy job (``kind``: its name in words, for the messages)."""

    def __init__(self, kind: str, workers: int = WORKERS, waiting: int = WAITING):
        self.kind = kind
        self.workers = workers
        self.max_waiting = waiting
        self.running = 0
        self._queue: collections.deque[asyncio.Future] = collections.deque()
        self.refused = 0            # jobs refused as busy (tests, status)
        self.done = 0               # jobs finished

    @property
    def waiting(self) -> int:
        return len(self._queue)

    def status(self) -> dict[str, Any]:
        return {"kind": self.kind, "running": self.running, "waiting": self.waiting,
                "max_running": self.workers, "max_waiting": self.max_waiting,
                "refused": self.refused, "done": self.done}

    async def run(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` in a worker thread when a slot is free; its result or exception.
        ToolError (429) when ``workers`` run and ``waiting`` wait already."""
        loop = asyncio.get_running_loop()
        if self.running >= self.workers:
            if len(self._queue) >= self.max_waiting:
                self.refused += 1
                raise ToolError("job", f"busy: {self.running} {self.kind} running and "
                                       f"{len(self._queue)} waiting (at most {self.workers} at "
                                       f"a time, {self.max_waiting} waiting): try again when "
                                       "one has finished", 429)
            gate = loop.create_future()
            self._queue.append(gate)
            try:
                await gate          # resolved by _release: the slot is handed over
            except asyncio.CancelledError:
                if gate in self._queue:
                    self._queue.remove(gate)
                elif gate.done() and not gate.cancelled():
                    self._release()  # handed the slot as we left: pass it on
                raise
        else:
            self.running += 1
        done = loop.create_future()

        def finish(ok: bool, value: Any) -> None:
            self.done += 1
            self._release()
            if not done.done():
                if ok:
                    done.set_result(value)
                else:
                    done.set_exception(value)

        def work() -> None:
            try:
                value, ok = fn(), True
            except BaseException as e:      # handed to the caller
                value, ok = e, False
            try:
                loop.call_soon_threadsafe(finish, ok, value)
            except RuntimeError:            # the loop closed meanwhile (shutdown)
                pass

        try:
            threading.Thread(target=work, name=f"job: {self.kind}", daemon=True).start()
        except BaseException:
            self._release()
            raise
        return await done

    def _release(self) -> None:
        """A slot freed: to the first one waiting (still there), else counted free."""
        while self._queue:
            gate = self._queue.popleft()
            if not gate.done():
                gate.set_result(None)
                return
        self.running -= 1


CHUNK_ROWS = 10_000   # rows per compiled call in a job: the call holds the interpreter


def run_in_chunks(est, t, gyr=None, acc=None, mag=None, ori=None, rows: int = CHUNK_ROWS):
    """``est.run(t, gyr, acc, mag, ori)`` over a whole recording, ``rows`` at a time (the
    estimator keeps its state from one call to the next, as the live ensemble's chunks
    do): a compiled run holds the interpreter's lock, so one call over a long
    recording would stall the event loop for its whole length; between chunks the loop
    gets its turn. The same result as one call."""
    import numpy as np
    from app.estimators import BatchResult

    n = len(t)
    if n <= rows:
        return est.run(t, gyr, acc, mag, ori)
    parts = [est.run(t[i:i + rows], *(None if x is None else x[i:i + rows]
                                      for x in (gyr, acc, mag, ori)))
             for i in range(0, n, rows)]
    return BatchResult(t=np.concatenate([p.t for p in parts]),
                       q=np.concatenate([p.q for p in parts]),
                       flags=np.concatenate([p.flags for p in parts]))
