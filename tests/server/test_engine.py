"""app.server.engine against the real server: the filter task cannot die. A client that
stops reading WS /ws/state is dropped and never holds up the filter; a step that raises
is counted and the stream goes on; the supervisor restarts the task and says so."""

from __future__ import annotations

import asyncio
import base64
import os
import socket

import httpx
import pytest

from app.estimators.base import Estimator
from app.estimators.phone import PhoneOrientation
from app.sources.simulate import simulate
from harness import Phone, running_server, wait_for


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with running_server(preset_dir=tmp_path_factory.mktemp("presets")) as s:
        yield s


@pytest.fixture()
def api(srv):
    with httpx.Client(base_url=srv.url, timeout=30.0) as c:
        yield c


def play(srv, api, lines) -> dict:
    n0 = api.get("/api/state").json()["counts"]["total_sessions"]
    with Phone(srv.phone_port) as ph:
        ph.send_lines(lines)        # a connection is a phone once it sends a valid sample
        wait_for(lambda: api.get("/api/state").json()["counts"]["total_sessions"] > n0, what="session")
    return wait_for(lambda: (lambda st: st if st["source"] == "phone-disconnected"
                             and st["counts"]["buffered"] == 0 and st["counts"]["queued"] == 0
                             else None)(api.get("/api/state").json()), what="end of stream")


def stuck_ws_client(port: int) -> socket.socket:
    """A WebSocket client that completes the handshake and then never reads (a laptop
    put to sleep): a tiny receive buffer, so the server's sends back up at once."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws/state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
               f"Origin: http://127.0.0.1:{port}\r\n\r\n").encode())
    assert b"101" in s.recv(200).split(b"\r\n")[0]
    return s


def test_a_stuck_websocket_client_is_dropped_and_the_filter_goes_on(srv, api):
    srv.engine.subscriber_backlog = 3          # drop after 3 unread messages (default 200)
    stuck = stuck_ws_client(srv.settings.port)
    try:
        wait_for(lambda: srv.engine.subscribers, what="the subscriber")
        lines = simulate(("still", "turn_z", "shake"), seed=3).lines()
        for _ in range(30):     # until the socket buffers (~2 MB here) are full: ~6 streams
            st = play(srv, api, lines)
            assert st["counts"]["samples"] == len(lines)
            if api.get("/api/health").json()["dropped_subscribers"] >= 1:
                break
        assert api.get("/api/health").json()["dropped_subscribers"] >= 1
        h = api.get("/api/health").json()
        assert h["status"] == "ok" and h["restarts"] == 0 and h["loop_errors"] == 0
        st = play(srv, api, lines)             # and every later sample is used
        assert st["counts"]["samples"] == len(lines) and st["initialized"]
    finally:
        stuck.close()
        srv.engine.subscriber_backlog = 200


class Raising(PhoneOrientation):
    """The phone estimator with a planted bug: it raises on ORI samples with x > 0.1."""

    _run_rows = Estimator._run_rows   # the generic loop over _step (the compiled run does not call it)

    def _step(self, t, gyr, acc, mag, ori, flags):
        if ori is not None and ori[1] > 0.1:
            raise RuntimeError("planted bug")
        super()._step(t, gyr, acc, mag, ori, flags)


def test_a_step_that_raises_is_counted_and_the_stream_goes_on(srv, api):
    eng = srv.engine
    eng.loop.call_soon_threadsafe(eng.core.ensemble.add, "raiser", "phone", None, Raising())
    wait_for(lambda: "raiser" in api.get("/api/params").json()["estimators"], what="the variant")
    try:
        lines = ["1000\tACC\t0\t0\t9.81", "1005\tORI\t0.99\t0.14\t0\t0", "1010\tORI\t1\t0\t0\t0",
                 "1020\tGYR\t0\t0\t0.1", "1030\tORI\t0.99\t0.14\t0\t0", "1040\tACC\t0\t0\t9.81"]
        st = play(srv, api, lines)
        assert st["estimators"]["raiser"]["step_errors"] == 2
        assert st["counts"]["total_step_errors"] >= 2
        assert st["counts"]["samples"] == len(lines)
        assert st["estimators"]["raiser"]["initialized"]          # the good ORI was used
        h = api.get("/api/health").json()
        assert h["status"] == "ok" and h["step_errors"] >= 2 and h["loop_errors"] == 0
        st = play(srv, api, simulate(("still",), seed=1).lines())
        assert st["initialized"] and st["estimators"]["raiser"]["q"] is not None
    finally:
        eng.loop.call_soon_threadsafe(eng.core.ensemble.remove, "raiser")
        wait_for(lambda: "raiser" not in api.get("/api/params").json()["estimators"], what="removed")


def test_the_supervisor_restarts_the_filter_task(srv, api):
    eng = srv.engine
    before = api.get("/api/health").json()["restarts"]
    eng.loop.call_soon_threadsafe(eng.inbox.put_nowait, None)   # not an item: the loop breaks
    h = wait_for(lambda: (lambda h: h if h["restarts"] > before else None)(
        api.get("/api/health").json()), what="the restart")
    assert h["status"] == "ok"
    assert "restarted" in api.get("/api/state").json()["status"]
    lines = simulate(("still",), seed=2).lines()
    st = play(srv, api, lines)
    assert st["counts"]["samples"] == len(lines) and st["initialized"]


def test_the_inbox_keeps_order_and_a_recording_sees_what_waits_for_the_filter():
    """Engine.queued_samples (what a recording begun mid-stream takes) lists the samples of
    one stream that wait for the filter task, in time order, and none of another stream's;
    the inbox hands items out in posting order, and a waiting get() wakes on the next put."""
    from collections import Counter

    from app.server.engine import Engine
    from app.server.settings import Settings
    from app.sources.sensorfusion import decode_lines

    samples = decode_lines(simulate(("still",), seed=3).lines()[:60], Counter())
    key = lambda x: (x.time_ms, x.tag)   # noqa: E731

    async def scenario():
        eng = Engine(Settings(source="none"))
        eng.bind(asyncio.get_running_loop())
        a = eng.open_session("demo", "a")
        eng.feed(a, samples)
        eng.close_session(a, "test")                # releases what the reorder buffer held
        b = eng.open_session("demo", "b")
        eng.feed(b, samples[:7])
        eng.close_session(b, "test")
        queued_a, queued_b = eng.queued_samples(a), eng.queued_samples(b)
        for queued, fed in ((queued_a, samples), (queued_b, samples[:7])):
            assert sorted(map(key, queued)) == sorted(map(key, fed))        # all of them,
            assert [x.time_ms for x in queued] == sorted(x.time_ms for x in queued)  # in order
        kinds = []
        while not eng.inbox.empty():
            kinds.append((await eng.inbox.get())[0])
        assert kinds[0] == "session" and kinds.count("session") == 2 and "samples" in kinds
        assert eng.queued_samples(a) == [] and eng.inbox.qsize() == 0
        waiter = asyncio.ensure_future(eng.inbox.get())
        await asyncio.sleep(0.01)
        assert not waiter.done()                    # an empty inbox waits ...
        eng.inbox.put_nowait(("change", None, None))
        assert (await asyncio.wait_for(waiter, 1.0))[0] == "change"   # ... and wakes on a put

    asyncio.run(scenario())
