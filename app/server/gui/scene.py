"""The viser 3D scene, drawn from the live core's :class:`~app.live.Snapshot`.

An ENU world (x east, y north, z up) with a grid and E/N/Up labels; the phone as a
flat slab in its sensor frame (x right, y top of the screen, z out of the screen): a
dark screen on the +z face, an orange band and the earpiece at the top (+y), the
sensor axes (x red, y green, z blue). Beside it:

- translucent phones for the phone's own estimate (orange) and, in the demo, the
  ground truth (green);
- the attitude uncertainty: a cone around each sensor axis whose half-widths are
  2σ of the rotation that moves that axis (from the estimator's ``attitude_cov``);
- two arrow pairs: gravity and magnetic field, the measured one (accelerometer /
  magnetometer turned to world coordinates by the estimate) beside the expected
  one (the estimator's references), so a disturbance shows as a mismatch;
- a floating status line (standstill, accelerometer / magnetometer disturbed with
  the reason and the value that tripped the gate): the GUI computes it once per
  refresh (:class:`Indicators`) and hands the same text to its pills and to
  :meth:`Scene.set_indicators`, so both always say the same.

Pure drawing: no filter state is touched. Quaternion math comes from
:mod:`app.quaternion`.
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import numpy as np

from app.estimators import Diagnostics, Reason
from app.live import Snapshot
from app.params import GRAVITY
from app.quaternion import Q, quat_from_matrix
from app.server import viser_adapter as va

W, H, D = 0.7, 1.4, 0.08            # phone size in scene units (x, y, z)
AXIS_LEN = 1.0
ARROW_LEN = 0.9
SIGMA_K = 2.0                        # cones show ±2σ
MAX_CONE_DEG = 60.0
GRAV_AT = np.array([-1.5, -1.4, 0.0])
MAG_AT = np.array([1.5, -1.4, 0.0])
CAMERA_AT = (2.1, -3.9, 2.5)
LOOK_AT = (0.0, -0.3, -0.2)
# The initial camera frames the phone and both arrows in a view this narrow (width / height:
# a projector's 1280x720 leaves the view about 580 px wide beside the panels, 0.86).
FRAMED_ASPECT = 0.86
# A view narrower than PORTRAIT_ASPECT at the initial camera is a phone held upright (the page
# gives the 3D view the screen's width: 0.45-0.6), and viser lays its control panel over the
# bottom 60 % of a phone's view, the phone in the middle under it: the camera moves back by
# FRAMED_ASPECT / aspect (the arrows stay in view) and the phone rises by PORTRAIT_LIFT of
# the view's half-height. (A desktop's or a tablet's view is wider; viser docks its panel
# beside the view there.)
PORTRAIT_ASPECT = 0.7
PORTRAIT_LIFT = 0.5
GREY = (150, 150, 150)
C_ACC, C_MAG, C_BAD = (0, 150, 255), (190, 0, 200), (230, 30, 30)
AXIS_COLORS = ((220, 40, 40), (40, 170, 40), (40, 80, 230))


def _cone_mesh(n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit cone: apex at the origin, axis +z, base of radius 1 at z = 1 (closed)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.ones(n)], axis=1)
    verts = np.vstack([[0.0, 0.0, 0.0], ring, [0.0, 0.0, 1.0]])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces.append((0, 1 + j, 1 + i))
        faces.append((n + 1, 1 + i, 1 + j))
    return verts.astype(np.float32), np.array(faces, dtype=np.uint32)


# For the cone around sensor axis i: columns = where the cone's local x, y, z go, and
# which rotation (about sensor axis k) widens it along its local x and y.
_CONE_FRAMES = (
    (np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float), (2, 1)),   # around x: along y, z
    (np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]], float), (0, 2)),   # around y: along z, x
    (np.eye(3), (1, 0)),                                             # around z: along x, y
)


def phone_body(scene, name: str, color, opacity=None) -> None:
    """A phone slab with its screen and top marked, under ``name``."""
    scene.add_box(f"{name}/body", color=color, dimensions=(W, H, D), opacity=opacity)
    scene.add_box(f"{name}/top", color=(255, 140, 0), dimensions=(W * 1.001, 0.06, D * 1.05),
                  position=(0.0, H / 2 - 0.03, 0.0), opacity=opacity)
    if opacity is None:
        scene.add_box(f"{name}/screen", color=(25, 35, 70), dimensions=(W - 0.07, H - 0.2, 0.01),
                      position=(0.0, -0.02, D / 2 + 0.004))
        scene.add_box(f"{name}/earpiece", color=(200, 200, 200), dimensions=(0.18, 0.025, 0.012),
                      position=(0.0, H / 2 - 0.1, D / 2 + 0.006))
        scene.add_icosphere(f"{name}/camera", radius=0.022, color=(10, 10, 10),
                            position=(0.14, H / 2 - 0.1, D / 2 + 0.006))
        # the back (-z): plain, a shade darker, with the rear camera near the top, so a
        # phone lying screen down reads as its back at a glance (no labels on it)
        scene.add_box(f"{name}/back", color=(160, 165, 175), dimensions=(W - 0.04, H - 0.04, 0.006),
                      position=(0.0, 0.0, -D / 2 - 0.003))
        scene.add_box(f"{name}/rear_camera", color=(40, 40, 45), dimensions=(0.16, 0.16, 0.014),
                      position=(W / 2 - 0.14, H / 2 - 0.14, -D / 2 - 0.007))  # top left seen from the back


class LoopSafeEvent(asyncio.Event):
    """The ``message_event`` of viser's broadcast buffer, safe to set from this server's
    event loop: viser sets it directly from the thread that queues a message (ours),
    while its senders wait on it in viser's own loop. ``asyncio.Event`` is not thread
    safe: our thread's ``set()`` iterating its waiters while viser's thread adds one
    raised "deque mutated during iteration" (logged as a failed pose, scene or GUI
    update, a few times in ten minutes under load), and the waiter being added was
    never woken while the event stayed set: with a single viewer, its sender waited
    for ever (a frozen 3D view). Here a ``set()`` from another thread is handed to
    viser's loop (``call_soon_threadsafe``); a set event is left as it is (as
    ``asyncio.Event.set`` does). viser reads the event only in its loop (waits, clears);
    :class:`_QuietLoop` reads ``is_set()`` from the queuing thread."""

    def __init__(self, home: asyncio.AbstractEventLoop):
        super().__init__()
        self._home = home

    def set(self) -> None:
        if self._value:
            return
        try:
            here = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if here is self._home:
            super().set()
            return
        try:
            self._home.call_soon_threadsafe(self._set_at_home)
        except RuntimeError:      # viser's loop closed (shutting down): nobody waits
            pass

    def _set_at_home(self) -> None:
        asyncio.Event.set(self)


class _QuietLoop:
    """viser's event loop as its broadcast buffer sees it: every attribute is the loop's,
    but a wake-up for the buffer's event (``call_soon_threadsafe(event.set)``, which viser
    schedules after every message queued outside an ``atomic()`` block) is left out while
    that event is set. A set event has no waiter (asyncio wakes them all when it is set);
    a sender clears it before it polls the buffer again, and a message is counted in the
    buffer before the wake-up is asked for, so nothing is sent later. What it saves is a
    write to viser's self-pipe per message: viser's thread woke and took the GIL from the
    event loop here 100 times a second for the pose alone."""

    def __init__(self, loop: asyncio.AbstractEventLoop, event: asyncio.Event):
        self._loop = loop
        self._event = event

    def call_soon_threadsafe(self, callback, *args, **kwargs):
        if callback == self._event.set and self._event.is_set():
            return None
        return self._loop.call_soon_threadsafe(callback, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._loop, name)


def loop_safe_wakeups(viewer) -> None:
    """Give a started ``viser.ViserServer``'s broadcast buffer a :class:`LoopSafeEvent`
    and a :class:`_QuietLoop` (viser's internals, through :mod:`app.server.viser_adapter`;
    before any viewer connects, so nobody waits on the old event)."""
    quiet_wakeups(va.broadcast_buffer(viewer), va.background_loop(viewer))


def quiet_wakeups(buf, home: asyncio.AbstractEventLoop, event_type=None) -> None:
    """The same for one of viser's ``AsyncMessageBuffer`` whose senders run in ``home``
    (``event_type``: a :class:`LoopSafeEvent` subclass, for tests)."""
    event, loop = va.buffer_wakeup(buf)
    if isinstance(event, LoopSafeEvent):
        return
    if event._waiters:
        raise RuntimeError("viser's senders already wait on the buffer's event")
    ev = (event_type or LoopSafeEvent)(home)
    if event.is_set():
        asyncio.Event.set(ev)
    va.set_buffer_wakeup(buf, ev, _QuietLoop(loop, ev))


def set_wxyz(handle, q) -> bool:
    """``handle.wxyz = q`` for a scene node, the cheap way (the estimate's pose goes out
    after every batch: 100 times a second for a phone). viser's setter casts through
    ``np.asarray`` and ``np.allclose`` per call; here the four plain floats are compared
    with the same tolerance (``allclose``'s rtol 1e-5, atol 1e-8), the handle's own copy
    is written (its getter and later setter calls see it) and the same
    ``SetOrientationMessage`` is queued by the same owner-stamping path (viser's
    internals, through :mod:`app.server.viser_adapter`). False when the pose was
    unchanged (nothing queued)."""
    if va.is_removed(handle):
        raise RuntimeError(f"Cannot assign to 'wxyz' on a removed {type(handle).__name__}.")
    v = tuple(map(float, q))
    if len(v) != 4:
        raise ValueError(f"Expected a quaternion of 4 values, got {len(v)}")
    cur = va.stored_wxyz(handle)
    c0, c1, c2, c3 = cur.tolist()
    if (abs(v[0] - c0) <= 1e-8 + 1e-5 * abs(c0) and abs(v[1] - c1) <= 1e-8 + 1e-5 * abs(c1)
            and abs(v[2] - c2) <= 1e-8 + 1e-5 * abs(c2) and abs(v[3] - c3) <= 1e-8 + 1e-5 * abs(c3)):
        return False
    cur[:] = v
    va.queue_scene_message(handle, va.set_orientation_message(handle, v))
    return True


def set_prop(handle, name: str, value) -> bool:
    """``setattr(handle, name, value)`` for a scene node's property (an arrow's
    ``points``, a cone's ``scale``), the cheap way: viser's generic setter builds its
    type hints (``npt.NDArray[...]``) anew on every call to cast the value; here the
    value takes the stored array's dtype (what that cast gives for these properties),
    an unchanged value sends nothing, and the same ``SceneNodeUpdateMessage`` is
    queued (with a copy: the stored array is updated in place later). Not for
    colours (viser converts those) or properties with setters of their own (``wxyz``:
    :func:`set_wxyz`). False when unchanged."""
    if va.is_removed(handle):
        raise RuntimeError(f"Cannot assign to {name!r} on a removed {type(handle).__name__}.")
    props = va.node_props(handle)
    cur = getattr(props, name)
    if isinstance(cur, np.ndarray):
        value = np.asarray(value, dtype=cur.dtype)
        if value.shape == cur.shape:
            if np.array_equal(cur, value):
                return False
            cur[...] = value
        else:
            setattr(props, name, value.copy())
        queued = value.copy()
    else:
        if cur == value:
            return False
        setattr(props, name, value)
        queued = value
    va.queue_scene_message(handle, va.scene_update_message(handle, {name: queued}))
    va.after_prop_assigned(handle, name)
    return True


def _arrow_points(vec: np.ndarray | None) -> np.ndarray:
    p = np.zeros((1, 2, 3), dtype=np.float32)
    if vec is not None and np.all(np.isfinite(vec)):
        p[0, 1] = vec
    return p


def narrow_view_camera(aspect: float, fov: float, position=CAMERA_AT, look_at=LOOK_AT):
    """The camera (position, look_at) for a view of ``aspect`` (width / height) with a
    vertical field of view ``fov`` (rad): the initial one unless the view is narrower than
    :data:`PORTRAIT_ASPECT`, then moved back along its line of sight by
    :data:`FRAMED_ASPECT` / ``aspect`` and panned down by :data:`PORTRAIT_LIFT` of the
    half-height there (the phone rises)."""
    p, at = np.asarray(position, float), np.asarray(look_at, float)
    if not 0.0 < aspect < PORTRAIT_ASPECT or not 0.0 < fov < np.pi:
        return p, at            # not narrow, or no canvas to frame
    f = at - p
    dist = float(np.linalg.norm(f)) * FRAMED_ASPECT / aspect
    f /= np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0]) - f[2] * f          # the screen's up, in the world
    up /= np.linalg.norm(up)
    at = at - PORTRAIT_LIFT * dist * np.tan(fov / 2.0) * up
    return at - dist * f, at


def at_initial_camera(position, look_at, tol: float = 1e-3) -> bool:
    """Whether a camera (position, look_at) is the initial one (:data:`CAMERA_AT`,
    :data:`LOOK_AT`), to ``tol`` of its distance: where viser's client puts it when it
    starts and on "Reset View"."""
    scale = tol * float(np.linalg.norm(np.subtract(CAMERA_AT, LOOK_AT)))
    return (float(np.linalg.norm(np.subtract(position, CAMERA_AT))) <= scale
            and float(np.linalg.norm(np.subtract(look_at, LOOK_AT))) <= scale)


def reframed_camera(aspect: float, fov: float, position, look_at):
    """The camera (position, look_at) a view of ``aspect`` and ``fov`` should be moved to,
    or None to leave it: a view at the initial camera gets :func:`narrow_view_camera` when
    that differs from it (a narrow view with a canvas); a camera the viewer has moved, a
    wide view and a view with no canvas yet (aspect 0) are left as they are."""
    if not at_initial_camera(position, look_at):
        return None
    framed = narrow_view_camera(aspect, fov)
    return None if at_initial_camera(*framed) else framed


def frame_narrow_view(client) -> None:
    """On a client's connection (viser calls it once the client's camera, with its canvas
    size, has come): a phone's upright view gets :func:`narrow_view_camera`, now and
    whenever its camera is back at the initial one (:func:`reframed_camera`). viser's
    client puts it there itself: on "Reset View", and when the scene's up direction or
    initial camera arrives, which can be after this hook has moved it (the phone-screen
    browser test once lost its framing so, with the suite on two workers)."""
    cam = client.camera

    def frame(_=None) -> None:
        try:
            to = reframed_camera(cam.aspect, cam.fov, cam.position, cam.look_at)
        except (AssertionError, ZeroDivisionError):
            return      # no canvas size yet
        if to is not None:
            with client.atomic():
                cam.position = to[0]        # (viser moves look_at with it: set it after)
                cam.look_at = to[1]

    cam.on_update(frame)
    frame()


class Scene:
    """Builds the scene once; :meth:`draw` updates it from a snapshot."""

    def __init__(self, server):
        self.server = server
        sc = server.scene
        sc.set_up_direction("+z")
        sc.add_grid("/world/grid", width=4.0, height=4.0, cell_size=0.25, section_size=1.0,
                    plane="xy", position=(0.0, 0.0, -0.9))
        axes = np.array([[[0, 0, -0.9], [2.1, 0, -0.9]], [[0, 0, -0.9], [0, 2.1, -0.9]],
                         [[0, 0, -0.9], [0, 0, 1.4]]], dtype=np.float32)
        sc.add_line_segments("/world/axes", points=axes,
                             colors=np.array([[[200, 60, 60]] * 2, [[60, 160, 60]] * 2,
                                              [[60, 90, 220]] * 2], dtype=np.uint8),
                             thickness=0.012)
        for text, pos in (("E", (2.25, 0, -0.9)), ("N", (0, 2.25, -0.9)), ("Up", (0, 0, 1.5))):
            sc.add_label(f"/world/label_{text}", text, position=pos, font_screen_scale=1.6,
                         anchor="center-center")
        # the estimate
        self.phone = sc.add_frame("/phone", show_axes=False)
        phone_body(sc, "/phone", (225, 225, 232))
        sc.add_frame("/phone/axes", axes_length=AXIS_LEN, axes_radius=0.018, origin_radius=0.03)
        # one label per axis at its tip, nothing else on the phone: labels face the
        # camera, so more of them overlap when the phone turns (the orange band and the
        # earpiece mark the top; the darker back with its camera marks the back)
        for i, text in enumerate(("x", "y (top)", "z (screen)")):
            pos = [0.0, 0.0, 0.0]
            pos[i] = AXIS_LEN + 0.12
            sc.add_label(f"/phone/axis_{'xyz'[i]}", text, position=tuple(pos), anchor="center-center")
        verts, faces = _cone_mesh()
        self.cones = []
        for i in range(3):
            R, _ = _CONE_FRAMES[i]
            self.cones.append(sc.add_mesh_simple(
                f"/phone/cone_{'xyz'[i]}", verts, faces, color=AXIS_COLORS[i], opacity=0.25,
                side="double", wxyz=tuple(quat_from_matrix(R)), scale=(0.01, 0.01, AXIS_LEN),
                cast_shadow=False, receive_shadow=False))
        # the phone's own estimate and the truth
        self.own = sc.add_frame("/phone_own", show_axes=False, visible=False)
        phone_body(sc, "/phone_own", (255, 150, 40), opacity=0.3)
        self.truth = sc.add_frame("/truth", show_axes=False, visible=False)
        phone_body(sc, "/truth", (60, 200, 90), opacity=0.3)
        # gravity and field arrows
        self.grav_expected = sc.add_arrows("/arrows/gravity_expected", _arrow_points(None),
                                           colors=GREY, position=tuple(GRAV_AT - [0.12, 0, 0]),
                                           shaft_radius=0.025, head_radius=0.06)
        self.grav = sc.add_arrows("/arrows/gravity", _arrow_points(None), colors=C_ACC,
                                  position=tuple(GRAV_AT), shaft_radius=0.025, head_radius=0.06)
        self.mag_expected = sc.add_arrows("/arrows/field_expected", _arrow_points(None),
                                          colors=GREY, position=tuple(MAG_AT - [0.12, 0, 0]),
                                          shaft_radius=0.025, head_radius=0.06)
        self.mag = sc.add_arrows("/arrows/field", _arrow_points(None), colors=C_MAG,
                                 position=tuple(MAG_AT), shaft_radius=0.025, head_radius=0.06)
        sc.add_label("/arrows/gravity_label", "gravity (up: specific force)\ngrey expected, blue measured (red: refused)",
                     position=tuple(GRAV_AT + [0, -0.25, 0]), anchor="top-center", font_screen_scale=0.8)
        sc.add_label("/arrows/field_label", "magnetic field\ngrey expected, purple measured (red: refused)",
                     position=tuple(MAG_AT + [0, -0.25, 0]), anchor="top-center", font_screen_scale=0.8)
        self.status = sc.add_label("/status", "", position=(0.0, 0.0, 1.25), anchor="bottom-center")
        self._status_text = ""
        self._want = {"own": True, "truth": True}
        self._has = {"own": False, "truth": False}
        self._shown = {"own": False, "truth": False}
        self._bad = {"acc": False, "mag": False}
        self._blank = {"acc": True, "mag": True}     # the measured arrow drawn empty
        self._expected: dict[str, np.ndarray] = {}
        self._cone_scale: list[tuple[float, ...]] = [()] * 3
        # the phone in the middle of the 3D view, the arrows beside it, the whole at a
        # projector's 1280x720 too (the view is then about 580 px wide beside the panels)
        server.initial_camera.position = CAMERA_AT
        server.initial_camera.look_at = LOOK_AT
        server.on_client_connect(frame_narrow_view)

    # ------------------------------------------------------------------ switches
    def show(self, what: str, on: bool) -> None:
        """Switch a part of the scene: ``own``, ``truth``, ``cones``, ``arrows``."""
        if what == "cones":
            for c in self.cones:
                c.visible = on
        elif what == "arrows":
            for h in (self.grav, self.grav_expected, self.mag, self.mag_expected):
                h.visible = on
        else:
            self._want[what] = on
            self._set_visible(what, on and self._has[what])

    def _set_visible(self, what: str, on: bool) -> None:
        if self._shown[what] != on:
            getattr(self, what).visible = on
            self._shown[what] = on

    # ------------------------------------------------------------------ drawing
    def draw_pose(self, q: np.ndarray) -> None:
        """Only the estimate's pose (cheap: called after every processed batch)."""
        set_wxyz(self.phone, q)

    def draw(self, s: Snapshot) -> None:
        """Update every moving part from the snapshot (one atomic viser update)."""
        R = Q(s.q)
        with self.server.atomic():
            set_wxyz(self.phone, s.q)
            for what, q in (("own", s.phone_q), ("truth", s.truth_q)):
                self._has[what] = q is not None
                if q is not None:
                    set_wxyz(getattr(self, what), q)
                self._set_visible(what, self._want[what] and q is not None)
            self._draw_cones(R, s.cov)
            self._draw_arrows(R, s)

    def set_indicators(self, ind: "Indicators") -> None:
        """The floating status line (the same text as the GUI's pills)."""
        text = ind.text()
        if text != self._status_text:
            self.status.text = text
            self._status_text = text

    def _draw_cones(self, R: np.ndarray, cov: np.ndarray | None) -> None:
        if cov is None:
            sig = np.zeros(3)
        else:
            cb = R.T @ np.asarray(cov) @ R
            sig = np.sqrt(np.clip(np.diag(cb), 0.0, None))
        lim = math.radians(MAX_CONE_DEG)
        for i, cone in enumerate(self.cones):
            a, b = _CONE_FRAMES[i][1]
            scale = (math.tan(min(SIGMA_K * sig[a], lim)) * AXIS_LEN,
                     math.tan(min(SIGMA_K * sig[b], lim)) * AXIS_LEN, AXIS_LEN)
            # σ settles within seconds: send a cone only when it visibly changes
            if not _close(scale, self._cone_scale[i], 1e-3):
                set_prop(cone, "scale", scale)
                self._cone_scale[i] = scale

    def _draw_arrows(self, R: np.ndarray, s: Snapshot) -> None:
        g0 = np.asarray(s.diag.g0 or (0.0, 0.0, GRAVITY), float)
        gn = float(np.linalg.norm(g0))
        self._set_expected("grav", self.grav_expected, g0 / gn * ARROW_LEN)
        if s.acc is not None:
            set_prop(self.grav, "points", _arrow_points(np.clip(R @ s.acc / gn, -2, 2) * ARROW_LEN))
            self._color("acc", self.grav, s.acc_flags, C_ACC)
            self._blank["acc"] = False
        else:
            self._clear("acc", self.grav)
        m0 = expected_field(s.diag)
        mn = float(np.linalg.norm(m0)) if m0 is not None else 50.0
        self._set_expected("mag", self.mag_expected, None if m0 is None else np.asarray(m0) / mn * ARROW_LEN)
        if s.mag is not None:
            set_prop(self.mag, "points", _arrow_points(np.clip(R @ s.mag / mn, -2, 2) * ARROW_LEN))
            self._color("mag", self.mag, s.mag_flags, C_MAG)
            self._blank["mag"] = False
        else:
            self._clear("mag", self.mag)

    def _clear(self, key: str, handle) -> None:
        """No measured arrow (the sensor stopped, or has not started): once, not a frame."""
        if not self._blank[key]:
            set_prop(handle, "points", _arrow_points(None))
            self._blank[key] = True

    def _set_expected(self, key: str, handle, vec) -> None:
        """Expected directions rarely change: send them only when they do."""
        pts = _arrow_points(vec)
        last = self._expected.get(key)
        if last is None or not _close(pts.ravel().tolist(), last.ravel().tolist(), 1e-3):
            set_prop(handle, "points", pts)
            self._expected[key] = pts

    def _color(self, sensor: str, handle, flags, good) -> None:
        """Red while the sensor's last sample was refused by a gate."""
        bad = flags is not None and flags.rejected(sensor)
        if bad != self._bad[sensor]:
            # an array: viser's property setter does not convert a tuple of colours
            handle.colors = np.array(C_BAD if bad else good, dtype=np.uint8)
            self._bad[sensor] = bad


def _close(a, b, atol: float) -> bool:
    """Same length and every element within ``atol`` (plain floats: cheaper than
    numpy for a handful of numbers)."""
    return len(a) == len(b) and all(abs(x - y) <= atol for x, y in zip(a, b))


def expected_field(diag: Diagnostics) -> np.ndarray | None:
    """The reference magnetic field in world coordinates (µT) from an estimator's
    diagnostics (``m0``: lab's nominal field, robust's learned reference), else None."""
    m0 = diag.m0
    return None if m0 is None else np.asarray(m0, float)


@dataclass(frozen=True)
class Indicators:
    """What the indicators say: standstill, and for a disturbed sensor the gate that
    refused it and the value (``"|a| = 14.2 m/s²"``), else None."""
    rest: bool = False
    acc: str | None = None
    mag: str | None = None
    aligning: bool = False
    waiting_for: str = "aligning…"     # what the estimate waits for while it has none

    def text(self) -> str:
        """OrientationView's indicators as one line."""
        parts = []
        if self.rest:
            parts.append("standstill")
        for sensor in ("acc", "mag"):
            v = getattr(self, sensor)
            if v is not None:
                parts.append(f"{sensor} disturbed: {v}")
        if self.aligning:
            parts.append(self.waiting_for)
        return " · ".join(parts)


def describe_rejection(sensor: str, f) -> str:
    """'|a| = 12.3 m/s²' and the like: the gate that refused and its value, with its unit,
    rounded to what the sensor can tell (the pills and the 3D label show this text)."""
    r: Reason = getattr(f, sensor)
    v = getattr(f, f"{sensor}_value")
    if not math.isfinite(v):
        return r.label
    if r == Reason.NORM:
        return f"|{'a' if sensor == 'acc' else 'm'}| = {v:.1f} {'m/s²' if sensor == 'acc' else 'µT'}"
    if r == Reason.FIELD:
        return f"L_k = {v:.1f} µT"
    if r == Reason.DIP:
        return f"dip off by {math.degrees(v):.1f}°"
    if r == Reason.NIS:
        return f"NIS = {v:.1f}"
    if r == Reason.ACCEL:
        return f"accelerating, {math.degrees(v):.0f}° off gravity"
    if r == Reason.TURN:
        return f"field turning {math.degrees(v):.0f}°/s more than the phone"
    if r == Reason.GAP:
        return f"gap of {v:.2f} s"
    if r in (Reason.NEW_FIELD, Reason.OFFSET):
        return f"{r.label.replace('_', ' ')} {v:.1f} µT"
    if r == Reason.RECOVER:
        return f"re-aligned by {math.degrees(v):.0f}°"
    return f"{r.label.replace('_', ' ')} {v:.3g}"
