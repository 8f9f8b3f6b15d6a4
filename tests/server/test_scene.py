"""app/server/gui/scene.py's wake-up of viser's senders from this server's thread."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np

from app.server.gui.scene import (CAMERA_AT, GRAV_AT, LOOK_AT, MAG_AT, PORTRAIT_ASPECT,
                                  LoopSafeEvent, _QuietLoop, at_initial_camera, narrow_view_camera,
                                  quiet_wakeups, reframed_camera)
from harness import running_server, view_xy


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


class _CountingEvent(LoopSafeEvent):
    """A LoopSafeEvent that counts the sets run in its loop (the wake-ups)."""
    sets_at_home = 0

    def set(self) -> None:
        if _in_loop():
            type(self).sets_at_home += 1
        super().set()


def _in_loop() -> bool:
    try:
        asyncio.get_running_loop()
        return True
    except RuntimeError:
        return False


def test_a_quiet_buffer_delivers_every_message_with_fewer_wakeups():
    """viser's own message buffer, its senders in their loop, fed from this thread in
    bursts and pauses: every message arrives (no sender left asleep with a message
    waiting), while a message queued when the event is already set wakes nobody."""
    from viser import _messages
    from viser.infra._async_message_buffer import AsyncMessageBuffer

    loop = asyncio.new_event_loop()
    th = threading.Thread(target=loop.run_forever, daemon=True)
    th.start()
    buf = AsyncMessageBuffer(loop, persistent_messages=True)
    quiet_wakeups(buf, loop, _CountingEvent)
    n = 1000
    got: set[str] = set()
    all_in = threading.Event()

    async def sender():                     # what viser's client connection does
        async for window in buf.window_generator(client_id=1):
            got.update(m.name for m in window)
            if len(got) == n:
                all_in.set()
                return

    fut = asyncio.run_coroutine_threadsafe(sender(), loop)
    try:
        for i in range(n):
            buf.push(_messages.SetOrientationMessage(f"/node{i}", (1.0, 0.0, 0.0, 0.0)))
            # a pose every ms (a sender sends 60 windows a second), and pauses in which
            # the sender goes idle and must be woken
            time.sleep(0.05 if i % 100 == 99 else 0.001)
        assert all_in.wait(30.0), f"{n - len(got)} messages never sent"
        # viser alone wakes its loop once per message; here about once per window
        assert _CountingEvent.sets_at_home < n / 2, _CountingEvent.sets_at_home
    finally:
        fut.cancel()
        loop.call_soon_threadsafe(loop.stop)
        th.join(5.0)


def test_the_servers_viewer_wakes_its_senders_the_loop_safe_way_and_quietly():
    """The server's viser buffer has both: the loop-safe event, and the loop that skips
    the wake-up of an event already set (one server start for both checks)."""
    with running_server() as srv:
        buf = srv.app.state.viewer._websock_server._broadcast_buffer
        assert isinstance(buf.message_event, LoopSafeEvent)
        assert isinstance(buf.event_loop, _QuietLoop) and buf.event_loop._event is buf.message_event


def test_every_indicator_value_has_its_unit_and_the_pill_says_what_the_3d_label_says():
    """'turn 1.83' (rad/s, no unit) was shown while the 3D label said '|m| = 71': every
    gate's value now comes with its unit, rounded, in the same words in both places."""
    import re
    from types import SimpleNamespace

    from app.estimators.base import Reason
    from app.server.gui.main import _indicators_html
    from app.server.gui.scene import Indicators, describe_rejection
    unit = re.compile(r"(µT|m/s²|°/s|°|\d s)")
    for r, v in ((Reason.NORM, 71.26), (Reason.FIELD, 55.0), (Reason.DIP, 0.2), (Reason.ACCEL, 0.3),
                 (Reason.TURN, 1.83), (Reason.GAP, 0.5), (Reason.NEW_FIELD, 48.0),
                 (Reason.OFFSET, 20.0), (Reason.RECOVER, 0.5)):
        text = describe_rejection("mag", SimpleNamespace(mag=r, mag_value=v))
        assert unit.search(text), (r, text)
        assert not re.search(r"\d\.\d{3,}", text), text          # rounded
    assert describe_rejection("mag", SimpleNamespace(mag=Reason.TURN, mag_value=1.83)) == \
        "field turning 105°/s more than the phone"
    assert describe_rejection("mag", SimpleNamespace(mag=Reason.NORM, mag_value=71.26)) == "|m| = 71.3 µT"
    ind = Indicators(rest=False, acc=None, mag="|m| = 71.3 µT")
    assert "mag disturbed: |m| = 71.3 µT" in ind.text()
    assert "mag disturbed: |m| = 71.3 µT" in _indicators_html(ind)


def test_the_calibration_read_out_rounds_to_what_the_sensors_tell(tmp_path):
    """g0 was printed as [0.0, 0.0, 9.812345678901234]: now to 0.01 m/s², m0 to 0.1 µT."""
    import re
    with running_server(source="none", preset_dir=tmp_path) as srv:
        tab = srv.app.state.toolkit_tab
        tab.tk.calibration.last = {
            "n_rows": 500, "duration_s": 5.0, "stationary": True, "warnings": [],
            "sensors": {"gyr": {"title": "gyroscope", "unit": "rad/s", "mean": [0.0325, 0.0, -0.001],
                                "std": [0.001] * 3, "drift_per_min": [0.0] * 3,
                                "normality": {"normal_5pct": [True, True, None]}}},
            "g0": [0.0, 0.0, 9.812345678901234], "m0": [0.0, 19.876543210987, -44.12345678901]}
        done = threading.Event()
        srv.engine.loop.call_soon_threadsafe(lambda: (tab._draw_calibration(True), done.set()))
        assert done.wait(10.0)
        text = tab.cal_md.content
        assert "g0 = (0.00, 0.00, 9.81) m/s²" in text and "m0 (formula 7) = (0.0, 19.9, -44.1) µT" in text
        # the gyroscope's mean in the filters' SI and as Tuning and the bias notice show it
        assert "mean (0.0325, 0, -0.001 = 1.86, 0, -0.0573 deg/s)" in text, text
        assert not re.search(r"\d\.\d{5,}", text), text


def test_a_portrait_view_shows_the_phone_above_the_panel_and_both_arrows():
    """A student's phone (portrait, 390x675 CSS px, viser's 75° field of view): the phone
    sits in the top 40 % of the view, above the control panel viser lays over the bottom
    60 % of a phone's view, and the two arrows stay within its width. The projector's view
    (0.86 beside the panels at 1280x720) and wider keep the initial camera."""
    fov = np.radians(75.0)
    for aspect in (0.0, PORTRAIT_ASPECT, 0.86, 1.0, 1.8):     # 0: no canvas yet
        p, at = narrow_view_camera(aspect, fov)
        assert np.allclose(p, CAMERA_AT) and np.allclose(at, LOOK_AT)
    for aspect in (390 / 675, 360 / 640, 0.45):
        p, at = narrow_view_camera(aspect, fov)
        x, y = view_xy((0.0, 0.0, 0.0), p, at, fov, aspect)
        assert 0.1 < y < 0.4 and 0.2 < x < 0.8, (aspect, x, y)
        for arrow in (GRAV_AT, MAG_AT):
            x, _ = view_xy(arrow, p, at, fov, aspect)
            assert 0.0 < x < 1.0, (aspect, arrow, x)
        # unchanged, the phone would be in the middle, under the panel
        x, y = view_xy((0.0, 0.0, 0.0), CAMERA_AT, LOOK_AT, fov, aspect)
        assert y > 0.4
        # the framed camera is no longer the initial one: it is framed once, not again
        assert not at_initial_camera(p, at)


def test_the_initial_camera_is_recognised_to_float32_not_a_moved_one():
    """The phone's view is framed when its camera is back at the initial one ("Reset View",
    the client's own reset): the pose as the browser reports it (float32, through viser's
    frame transform) counts; a camera the viewer moved by a centimetre does not."""
    p32 = np.asarray(CAMERA_AT, np.float32).astype(float)
    at32 = np.asarray(LOOK_AT, np.float32).astype(float)
    assert at_initial_camera(CAMERA_AT, LOOK_AT) and at_initial_camera(p32, at32)
    assert not at_initial_camera(np.add(CAMERA_AT, (0.01, 0.0, 0.0)), LOOK_AT)
    assert not at_initial_camera(CAMERA_AT, np.add(LOOK_AT, (0.0, 0.0, 0.01)))


def test_only_a_narrow_view_at_the_initial_camera_is_moved():
    """What the camera watcher does with each camera message: a phone's view at the initial
    camera is framed; a framed or moved camera, a projector's view and a view with no canvas
    yet (aspect 0) are left alone, so setting the camera never answers its own message."""
    fov = np.radians(75.0)
    framed = reframed_camera(0.5, fov, CAMERA_AT, LOOK_AT)
    assert framed is not None and not at_initial_camera(*framed)
    assert reframed_camera(0.5, fov, *framed) is None                  # framed: once
    assert reframed_camera(0.5, fov, (3.0, 3.0, 1.5), (0.0, 0.0, 0.0)) is None   # moved
    for aspect in (0.0, PORTRAIT_ASPECT, 0.86, 1.8):                   # no canvas, or wide
        assert reframed_camera(aspect, fov, CAMERA_AT, LOOK_AT) is None, aspect
