"""app/server/viser_adapter.py: every viser internal orientlab uses, against a real
``viser.ViserServer``; and no other module under ``app/`` reaches into viser's internals.

Run this first when viser is upgraded: a failure names the internal that moved.
"""

from __future__ import annotations

import ast
import asyncio
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import viser
import websockets.sync.client
import zstandard

from app.server import viser_adapter as va
from harness import free_port

APP = Path(__file__).resolve().parents[2] / "app"
ADAPTER = APP / "server" / "viser_adapter.py"


def _wait_for(cond, timeout: float = 10.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


class Recorder:
    """What the adapter's WebSocket hooks saw (registered before any client connects)."""

    def __init__(self, viewer):
        self.viewer = viewer
        self.paths: dict[int, str] = {}
        self.gone: list[int] = []
        va.on_websocket_connect(viewer, self._connect)
        va.on_websocket_disconnect(viewer, self._disconnect)

    async def _connect(self, conn) -> None:
        live = va.websocket_connection(self.viewer, conn.client_id)
        self.paths[conn.client_id] = live.request.path

    async def _disconnect(self, conn) -> None:
        self.gone.append(conn.client_id)


@pytest.fixture(scope="module")
def server():
    """A real viser server on a free loopback port (stopped at the end), with the
    adapter's connect and disconnect hooks in place."""
    viewer = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        yield viewer, Recorder(viewer)
    finally:
        viewer.stop()


@pytest.fixture
def viewer(server):
    return server[0]


class Client:
    """A bare viser client in a thread (viser's WebSocket protocol): keeps every message
    it receives, decoded."""

    def __init__(self, viewer, path: str = "/"):
        self.url = f"ws://127.0.0.1:{viewer.get_port()}{path}"
        self.messages: list[dict] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.ws = websockets.sync.client.connect(
            self.url, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
            max_size=None)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        # viser counts a client as connected from its first camera message
        from viser import _messages
        self.send(_messages.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, 1.0), fov=1.0, near=0.01,
            far=100.0, image_height=400, image_width=600, look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0)))

    def _run(self) -> None:
        dz = zstandard.ZstdDecompressor()
        while not self._stop.is_set():
            try:
                raw = self.ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except websockets.exceptions.ConnectionClosed:
                return
            n_inner = int.from_bytes(raw[:8], "little")
            n_comp = int.from_bytes(raw[8:16], "little")
            inner = dz.decompress(raw[16:16 + n_comp], max_output_size=n_inner)
            with self._lock:
                self.messages.extend(msgspec.msgpack.decode(inner)["messages"])

    def send(self, msg) -> None:
        self.ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))

    def got(self, pred) -> list[dict]:
        with self._lock:
            return [m for m in self.messages if pred(m)]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.ws.close()


def _gui_update(uuid, key):
    return lambda m: (m.get("type") == "GuiUpdateMessage" and m.get("uuid") == uuid
                      and key in m.get("updates", {}))


# ---------------------------------------------------------------- check()

def test_check_passes_on_the_installed_viser(viewer):
    va.check()
    va.check(viewer)


def test_check_names_what_is_missing(monkeypatch):
    from viser._scene_api import SceneApi
    monkeypatch.delattr(SceneApi, "_queue_scene_message")
    with pytest.raises(va.ViserInternalsError, match=r"SceneApi\._queue_scene_message"):
        va.check()


def test_check_on_a_server_names_a_missing_live_attribute(viewer, monkeypatch):
    monkeypatch.delattr(va.websocket_server(viewer), "_live_connections")
    with pytest.raises(va.ViserInternalsError, match=r"WebsockServer\._live_connections"):
        va.check(viewer)


def test_a_function_whose_internal_is_gone_fails_clearly():
    gone = object()
    for fn, piece in ((va.websocket_server, "_websock_server"), (va.is_removed, "removed"),
                      (va.handle_value, "value"), (va.stored_wxyz, "wxyz"),
                      (va.queue_update, "_queue_update")):
        args = (gone, "data", 1) if fn is va.queue_update else (gone,)
        with pytest.raises(va.ViserInternalsError, match=piece):
            fn(*args)
    with pytest.raises(va.ViserInternalsError, match="_websock_connection"):
        va.queue_to_client(gone, va.gui_update_message("x", {"disabled": True}))


# ---------------------------------------------------------------- the WebSocket server

def test_the_websocket_server_its_loop_and_its_buffer_are_found(viewer):
    ws = va.websocket_server(viewer)
    assert isinstance(ws, viser.infra.WebsockServer)
    loop = va.background_loop(viewer)
    assert isinstance(loop, asyncio.AbstractEventLoop) and loop.is_running()
    buf = va.broadcast_buffer(viewer)
    event, buf_loop = va.buffer_wakeup(buf)
    assert isinstance(event, asyncio.Event)
    assert buf_loop is loop          # viser's own (app's scene wraps it; not this server)


def test_the_buffers_wakeup_is_replaced():
    from viser.infra._async_message_buffer import AsyncMessageBuffer
    loop = asyncio.new_event_loop()
    try:
        buf = AsyncMessageBuffer(loop, persistent_messages=True)
        ev, marker = asyncio.Event(), object()
        va.set_buffer_wakeup(buf, ev, marker)
        assert va.buffer_wakeup(buf) == (ev, marker)
        assert buf.message_event is ev and buf.event_loop is marker
    finally:
        loop.close()


def test_message_classes_and_messages():
    got = va.message_classes(("GuiUpdateMessage", "NoSuchMessage", "SceneNodeClickMessage"))
    assert [c.__name__ for c in got] == ["GuiUpdateMessage", "SceneNodeClickMessage"]
    m = va.gui_update_message("u1", {"disabled": True})
    assert isinstance(m, va.GuiUpdateMessage) and m.uuid == "u1" and m.updates == {"disabled": True}


# ---------------------------------------------------------------- GUI handles

def test_gui_input_handles_and_their_values(viewer):
    h = viewer.gui.add_slider("adapter slider", min=0, max=10, step=1, initial_value=3)
    uuid = va.handle_uuid(h)
    assert (uuid, h) in va.gui_input_handles(viewer)
    assert va.gui_input_handle(viewer, uuid) is h
    assert va.gui_input_handle(viewer, "no such uuid") is None
    assert va.handle_value(h) == h.value == 3
    h.value = 7
    assert va.handle_value(h) == h.value == 7
    assert va.is_removed(h) is False
    md = viewer.gui.add_markdown("not an input")
    assert all(x is not md for _, x in va.gui_input_handles(viewer))
    # a progress bar is listed for its value, but has no disabled property to show
    bar = viewer.gui.add_progress_bar(30.0)
    assert (va.handle_uuid(bar), bar) in va.gui_input_handles(viewer)
    assert va.can_be_disabled(h) and not va.can_be_disabled(bar)
    h.remove()
    assert va.is_removed(h) is True


# ---------------------------------------------------------------- scene nodes

def test_a_scene_nodes_orientation_and_props_through_the_adapter(viewer):
    frame = viewer.scene.add_frame("/adapter/frame", show_axes=False)
    stored = va.stored_wxyz(frame)
    assert np.shares_memory(stored, frame.wxyz)        # the handle's own copy
    q = (0.5, 0.5, -0.5, 0.5)
    stored[:] = q
    va.queue_scene_message(frame, va.set_orientation_message(frame, q))
    np.testing.assert_allclose(frame.wxyz, q)
    msg = va.set_orientation_message(frame, q)
    assert isinstance(msg, va.SetOrientationMessage) and msg.name == "/adapter/frame"
    # the scene module's cheap setter, built on the adapter
    from app.server.gui.scene import set_prop, set_wxyz
    q2 = (0.0, 1.0, 0.0, 0.0)
    assert set_wxyz(frame, q2) is True
    np.testing.assert_allclose(frame.wxyz, q2)
    assert set_wxyz(frame, q2) is False                # unchanged: nothing queued
    box = viewer.scene.add_box("/adapter/box", color=(1, 2, 3), dimensions=(1.0, 2.0, 3.0))
    assert va.node_props(box) is not None
    np.testing.assert_allclose(va.node_props(box).dimensions, box.dimensions)
    assert set_prop(box, "dimensions", (4.0, 5.0, 6.0)) is True
    np.testing.assert_allclose(box.dimensions, (4.0, 5.0, 6.0))
    up = va.scene_update_message(box, {"dimensions": (1.0, 1.0, 1.0)})
    assert isinstance(up, va.SceneNodeUpdateMessage) and up.name == "/adapter/box"
    va.after_prop_assigned(box, "dimensions")          # viser's hook: runs, no error
    assert va.is_removed(box) is False
    box.remove()
    assert va.is_removed(box) is True


# ---------------------------------------------------------------- end to end

def test_messages_reach_the_right_clients_and_incoming_ones_are_wrapped(server):
    viewer, rec = server
    h = viewer.gui.add_slider("e2e slider", min=0, max=10, step=1, initial_value=1)
    uuid = va.handle_uuid(h)
    frame = viewer.scene.add_frame("/adapter/e2e", show_axes=False)
    seen = []

    def wrap(cb):            # viser's handler may be a coroutine function (1.1's is)
        if asyncio.iscoroutinefunction(cb):
            async def spy(client_id, message):
                seen.append((client_id, message.uuid, dict(message.updates)))
                return await cb(client_id, message)
        else:
            def spy(client_id, message):
                seen.append((client_id, message.uuid, dict(message.updates)))
                return cb(client_id, message)
        return spy

    assert va.wrap_incoming_handlers(viewer, va.GuiUpdateMessage, wrap) is True
    never = type("NeverRegistered", (), {})
    assert va.wrap_incoming_handlers(viewer, never, wrap) is False

    a = Client(viewer, "/?token=abc")
    b = Client(viewer)
    try:
        clients = _wait_for(lambda: len(viewer.get_clients()) >= 2 and viewer.get_clients(),
                            what="two clients")
        # the connect hook saw each connection's upgrade request
        assert any("token=abc" in p for p in rec.paths.values())
        id_a = next(cid for cid, p in rec.paths.items() if "token=abc" in p)
        id_b = next(cid for cid in clients if cid != id_a)
        # wait until both have the GUI (the slider's creation)
        for c in (a, b):
            _wait_for(lambda c=c: c.got(lambda m: m.get("type") == "GuiSliderMessage"
                                        or m.get("uuid") == uuid), what="the GUI")
        # one client only
        va.queue_to_client(clients[id_a], va.gui_update_message(uuid, {"disabled": True}))
        _wait_for(lambda: a.got(_gui_update(uuid, "disabled")), what="A's private update")
        # everyone: a handle's own queued update, and a pose through the scene path
        va.queue_update(h, "hint", "from the adapter")
        va.queue_scene_message(frame, va.set_orientation_message(frame, (0.0, 0.0, 1.0, 0.0)))
        for c in (a, b):
            _wait_for(lambda c=c: c.got(_gui_update(uuid, "hint")), what="the broadcast")
            got = _wait_for(lambda c=c: c.got(lambda m: m.get("type") == "SetOrientationMessage"
                                              and m.get("name") == "/adapter/e2e"),
                            what="the pose")
            assert list(got[-1]["wxyz"]) == [0.0, 0.0, 1.0, 0.0]
        assert not b.got(_gui_update(uuid, "disabled"))
        # an incoming change goes through the wrapped handler, then viser's own
        b.send(va.gui_update_message(uuid, {"value": 6}))
        _wait_for(lambda: h.value == 6, what="the slider's change")
        assert (id_b, uuid, {"value": 6}) in seen
    finally:
        a.close()
        b.close()
    _wait_for(lambda: id_a in rec.gone and id_b in rec.gone, what="the disconnect hook")


# ---------------------------------------------------------------- nowhere else

INTERNAL_ATTRS = frozenset({
    "_impl", "_websock_server", "_websock_connection", "_websock_interface",
    "_broadcast_buffer", "_background_event_loop", "_gui_input_handle_from_uuid",
    "_queue_update", "_queue_scene_message", "_live_connections", "_incoming_handlers",
    "_on_prop_assigned", "_client_state_from_id", "message_event", "flush_event",
})


def _internal_module(name: str | None) -> bool:
    """``viser._messages``, ``viser.infra._infra``, ``viser.infra``: viser's private
    modules (viser's public API is the top-level ``viser`` package)."""
    if not name:
        return False
    parts = name.split(".")
    return parts[0] == "viser" and any(p.startswith("_") or p == "infra" for p in parts[1:])


def viser_internals_in(source: str, filename: str = "<source>") -> list[str]:
    """Every use of viser's internals in a module's source: imports of viser's private
    modules, and accesses of :data:`INTERNAL_ATTRS` (``x.attr`` or ``getattr(x,
    "attr")`` and its kin)."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        where = f"{filename}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Import):
            found += [f"{where}: import {a.name}" for a in node.names if _internal_module(a.name)]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and _internal_module(node.module):
                found.append(f"{where}: from {node.module} import ...")
            elif node.level == 0 and node.module == "viser":
                found += [f"{where}: from viser import {a.name}" for a in node.names
                          if a.name.startswith("_") or a.name == "infra"]
        elif isinstance(node, ast.Attribute):
            if node.attr in INTERNAL_ATTRS:
                found.append(f"{where}: .{node.attr}")
            elif (node.attr.startswith("_") or node.attr == "infra") and \
                    isinstance(node.value, ast.Name) and node.value.id == "viser":
                found.append(f"{where}: viser.{node.attr}")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id in ("getattr", "setattr", "hasattr", "delattr") and \
                len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and \
                node.args[1].value in INTERNAL_ATTRS:
            found.append(f"{where}: {node.func.id}(..., {node.args[1].value!r})")
    return found


@pytest.mark.parametrize("snippet", [
    "x._impl.value",
    "h = viewer._websock_server",
    "from viser import _messages",
    "from viser import _messages as m",
    "import viser._messages",
    "from viser.infra._infra import WebsockServer",
    "import viser\nviser._messages.GuiUpdateMessage",
    "q = getattr(handle, '_queue_update', None)",
    "buf.message_event = ev",
    "client._websock_connection.queue_message(m)",
])
def test_the_scanner_finds_viser_internals(snippet):
    assert viser_internals_in(snippet)


@pytest.mark.parametrize("snippet", [
    "import viser\nviser.ViserServer(port=1)",
    "from viser import GuiUplotHandle",
    "self._impl_cache = 1\nx._implode()",
    "from app.server import viser_adapter as va\nva.queue_update(h, 'data', 1)",
    "from . import _messages",        # a relative import is the project's own
])
def test_the_scanner_leaves_public_use_alone(snippet):
    assert viser_internals_in(snippet) == []


def test_only_the_adapter_uses_viser_internals():
    assert ADAPTER.is_file()
    offenders = []
    for path in sorted(APP.rglob("*.py")):
        if path == ADAPTER:
            continue
        offenders += viser_internals_in(path.read_text(encoding="utf-8"),
                                        str(path.relative_to(APP.parent)))
    assert offenders == [], ("viser internals outside app/server/viser_adapter.py (move them "
                             "into the adapter):\n" + "\n".join(offenders))


def test_the_adapter_itself_is_seen_by_the_scanner():
    """The scanner does find the adapter's internals (it would find another module's)."""
    assert viser_internals_in(ADAPTER.read_text(encoding="utf-8"))
