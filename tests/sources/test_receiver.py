"""The phone receiver's robustness, against the real server over loopback TCP:
bounded line buffer, disconnect mid-line, EOF and reconnect, second phone."""

from __future__ import annotations

import time

import httpx
import pytest

from harness import Phone, running_server, wait_for
from app.sources.sensorfusion import LineSplitter
from app.sources.simulate import simulate


# ------------------------------------------------------------------ the line splitter

def test_splitter_accepts_every_line_ending_across_chunks():
    sp = LineSplitter(100)
    out = sp.feed(b"1\tACC\t1\t2\t3\r\n2\tGYR")
    out += sp.feed(b"\t1\t2\t3\r")
    out += sp.feed(b"\n3\tMAG\t1\t2\t3\r4\tACC")
    assert out == [b"1\tACC\t1\t2\t3", b"2\tGYR\t1\t2\t3", b"3\tMAG\t1\t2\t3"]
    assert sp.pending == b"4\tACC"


def test_splitter_bounds_an_unfinished_line_and_keeps_the_good_ones():
    sp = LineSplitter(1000)
    assert sp.feed(b"good 1\n" + b"x" * 900) == [b"good 1"]
    assert sp.overflows == 0
    assert sp.feed(b"x" * 200) == []          # over the bound: dropped, counted
    assert sp.overflows == 1 and sp.pending == b""
    assert sp.feed(b"x" * 5000) == []         # still the same over-long line
    assert sp.feed(b"xx\ngood 2\ngo") == [b"good 2"]   # its end is dropped too
    assert sp.overflows == 1 and sp.pending == b"go"
    # an over-long line that arrives whole in one chunk is dropped the same way
    assert sp.feed(b"ne\n" + b"y" * 1500 + b"\nfine\n") == [b"gone", b"fine"]
    assert sp.overflows == 2


# ------------------------------------------------------------------ the real server

@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with running_server(phone_idle_s=1.0, preset_dir=tmp_path_factory.mktemp("p")) as s:
        yield s


@pytest.fixture()
def api(srv):
    with httpx.Client(base_url=srv.url, timeout=30.0) as c:
        yield c


def state(api):
    return api.get("/api/state").json()


def sessions(api) -> int:
    return state(api)["counts"]["total_sessions"]


def finished(api):
    st = state(api)
    c = st["counts"]
    return st if st["source"] == "phone-disconnected" and c["buffered"] == 0 and c["queued"] == 0 else None


LINES = simulate(("still",), seed=11).lines()


def test_ten_megabyte_line_closes_only_that_connection(srv, api):
    n0 = sessions(api)
    too_long0 = state(api)["counts"]["total_too_long"]
    with Phone(srv.phone_port) as ph:
        ph.send_lines(LINES[:50])     # a connection is a phone once it sends a valid sample
        wait_for(lambda: sessions(api) > n0, what="session")
        try:
            ph.send_bytes(b"1" * (10 * 1024 * 1024))
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server hung up while we were still sending: that is the point
        assert ph.closed_by_server()
    st = wait_for(lambda: finished(api), what="closed session")
    assert st["counts"]["total_too_long"] == too_long0 + 1
    assert st["counts"]["malformed_by_reason"].get("too_long") == 1
    assert st["counts"]["samples"] == 50
    assert "longer than" in st["status"]
    # the server is fine: the next phone streams normally
    with Phone(srv.phone_port) as ph:
        ph.send_lines(LINES)
        wait_for(lambda: sessions(api) > n0 + 1, what="second session")
    st = wait_for(lambda: finished(api), what="second stream")
    assert st["counts"]["samples"] == len(LINES)
    assert api.get("/api/health").json()["status"] == "ok"


def test_disconnect_mid_line_then_reconnect(srv, api):
    n0 = sessions(api)
    with Phone(srv.phone_port) as ph:
        ph.send_lines(LINES[:200])
        wait_for(lambda: sessions(api) > n0, what="session")
        ph.send_bytes(LINES[200][:9].encode())   # cut in the middle of a line
    st = wait_for(lambda: finished(api), what="EOF noticed")
    assert st["counts"]["samples"] == 200
    assert st["counts"]["malformed_by_reason"] == {"truncated": 1}
    assert "disconnected" in st["status"]
    t_last = st["t"]
    # the last state is kept ...
    assert state(api)["t"] == t_last and state(api)["q"] == st["q"]
    # ... and the next connection is accepted without a restart
    with Phone(srv.phone_port) as ph:
        ph.send_lines(LINES[:300], end="\r\n")
        wait_for(lambda: sessions(api) > n0 + 1, what="next session")
    st = wait_for(lambda: finished(api), what="next stream")
    assert st["counts"]["samples"] == 300 and st["counts"]["malformed"] == 0


def test_second_phone_is_refused_while_one_streams(srv, api):
    n0 = sessions(api)
    refused0 = state(api)["counts"]["total_refused"]
    slot0 = srv.app.state.slot.status()["refused"]
    with Phone(srv.phone_port) as first:
        first.send_lines(LINES[:100])
        wait_for(lambda: sessions(api) > n0, what="first session")
        with Phone(srv.phone_port) as second:
            assert second.closed_by_server()            # refused at once
            assert state(api)["counts"]["total_refused"] == refused0 + 1
            # and the slot's status says so (the Connect tab's "refused N×"): it did not for
            # a Sensor Fusion phone, only for the push apps
            slot = srv.app.state.slot.status()
            assert slot["refused"] == slot0 + 1 and "another phone" in slot["last_refusal"]
        first.send_lines(LINES[100:300])                  # the first one streams on
        wait_for(lambda: state(api)["counts"]["samples"] >= 250, what="first streams on")
        assert state(api)["source"] == "phone"
    st = wait_for(lambda: finished(api), what="first leaves")
    assert st["counts"]["samples"] == 300
    assert sessions(api) == n0 + 1


def test_silent_phone_is_taken_over(srv, api):
    """A connection silent for phone_idle_s (1 s here: a phone that lost Wi-Fi without
    closing) gives way to a new phone."""
    n0 = sessions(api)
    with Phone(srv.phone_port) as first:
        first.send_lines(LINES[:50])
        wait_for(lambda: sessions(api) > n0, what="first session")
        wait_for(lambda: state(api)["counts"]["samples"] >= 1, what="first samples")
        time.sleep(1.5)                                   # silent longer than phone_idle_s
        with Phone(srv.phone_port) as second:
            second.send_lines(LINES[:120])
            wait_for(lambda: sessions(api) > n0 + 1, what="takeover")
            assert first.closed_by_server()
        st = wait_for(lambda: finished(api), what="second stream")
        assert st["counts"]["samples"] == 120
