"""Every use of viser's internals, in one place: a viser upgrade touches this file.

orientlab leans on viser 1.1 beyond its public API in four places, each for a reason
its public API cannot serve:

- **the watch-only guard** (:func:`app.server.access.guard_viewer`): it needs the
  viewer's WebSocket server (to see a connection's URL and Origin before any message
  flows, and to filter incoming GUI messages per client) and sends a GUI update to
  *one* client (controls shown disabled, a refused change set back);
- **the wake-ups of viser's senders** (:func:`app.server.gui.scene.loop_safe_wakeups`):
  the broadcast buffer's event and loop are replaced by loop-safe, quiet ones;
- **the cheap updates** (:func:`app.server.gui.scene.set_wxyz`, ``set_prop``,
  :func:`app.server.gui.plots.send_data`): the scene pose 100 times a second and the
  plots' pre-encoded data are queued without viser's per-call casting;
- **the watch-only page's slider boxes** (:func:`show_slider_boxes_disabled`): a style
  for the client's own page, written against its DOM.

Every function below names the internal it relies on (its docstring's "Relies on").
:func:`check` verifies that all of them exist in the installed viser and raises
:class:`ViserInternalsError` naming every missing piece; each function also fails with
that error (not a bare ``AttributeError``) when its internal is gone. Everywhere else
in ``app/`` uses viser's public API only; ``tests/server/test_viser_adapter.py`` pins
both (it fails if another module reaches into viser's internals).

Upgrading viser: run ``tests/server/test_viser_adapter.py`` first (it starts a real
``viser.ViserServer``), then ``tests/server/test_faults.py``, ``tests/server/test_scene.py``,
``tests/server/test_viewer_cost.py`` and ``tests/server/test_plots_browser.py``.
"""

from __future__ import annotations

import asyncio
from typing import Any, Callable, Iterable

import viser

try:
    from viser import _messages
except ImportError:  # pragma: no cover - another viser: check() names what is missing
    _messages = None

# ---------------------------------------------------------------- message classes
# Re-exported for the callers (viser's ``_messages`` module is private); None if the
# installed viser lacks one (check() says so; the functions below raise).
GuiUpdateMessage = getattr(_messages, "GuiUpdateMessage", None)
SetOrientationMessage = getattr(_messages, "SetOrientationMessage", None)
SceneNodeUpdateMessage = getattr(_messages, "SceneNodeUpdateMessage", None)
GuiBaseProps = getattr(_messages, "GuiBaseProps", None)


class ViserInternalsError(RuntimeError):
    """The installed viser lacks an internal orientlab relies on (see the module doc)."""


def _missing(piece: str, exc: BaseException | None = None) -> ViserInternalsError:
    return ViserInternalsError(
        f"viser {getattr(viser, '__version__', '?')} has no {piece}, which orientlab relies "
        f"on (app/server/viser_adapter.py is written for viser 1.1)"
        + (f": {exc}" if exc is not None else ""))


def message_classes(names: Iterable[str]) -> tuple[type, ...]:
    """viser's message classes of these names that exist in the installed viser (a
    name viser does not have is left out).

    Relies on: ``viser._messages``."""
    if _messages is None:
        raise _missing("viser._messages")
    return tuple(getattr(_messages, n) for n in names if hasattr(_messages, n))


def gui_update_message(uuid: str, updates: dict) -> Any:
    """A ``GuiUpdateMessage``: set these props (``{"value": ..., "disabled": ...}``) of
    the GUI element ``uuid``.

    Relies on: ``viser._messages.GuiUpdateMessage(uuid, updates)``."""
    if GuiUpdateMessage is None:
        raise _missing("viser._messages.GuiUpdateMessage")
    return GuiUpdateMessage(uuid, updates)


# ---------------------------------------------------------------- the WebSocket server

def websocket_server(viewer) -> Any:
    """The ``viser.infra.WebsockServer`` behind a ``viser.ViserServer``.

    Relies on: ``ViserServer._websock_server``."""
    try:
        return viewer._websock_server
    except AttributeError as e:
        raise _missing("ViserServer._websock_server", e) from e


def on_broadcast(viewer, cb: Callable[[Any], None]) -> None:
    """Call ``cb(message)`` after each message the server queues for every client (the
    shared GUI's and the scene's), on the thread that queued it: ``cb`` must be cheap.

    Relies on: the shared GUI and scene sending through ``WebsockServer.queue_message``,
    looked up on the server at every send (``gui_api._websock_interface.queue_message``)."""
    server = websocket_server(viewer)
    try:
        queue = server.queue_message
    except AttributeError as e:
        raise _missing("WebsockServer.queue_message", e) from e

    def queue_message(message) -> None:
        queue(message)
        cb(message)

    server.queue_message = queue_message


def enabled_input(message) -> str | None:
    """The uuid of the GUI input an outgoing ``message`` shows enabled, else None: an
    update that sets ``disabled`` to False, or an input added enabled.

    Relies on: ``GuiUpdateMessage.updates`` and the add messages' ``props``
    (a ``GuiBaseProps`` with ``disabled``) beside their ``uuid``."""
    if GuiUpdateMessage is not None and isinstance(message, GuiUpdateMessage):
        return message.uuid if message.updates.get("disabled") is False else None
    props = getattr(message, "props", None)
    if GuiBaseProps is not None and isinstance(props, GuiBaseProps) and not props.disabled:
        return getattr(message, "uuid", None)
    return None


# viser's slider (its client's ``Slider.tsx``) hands ``disabled`` to its track only: the
# number box beside it stays editable. This style, on a watch-only client's page only,
# shows that box as disabled and takes the pointer off it. A value typed into it anyway
# (the keyboard can still reach it) is refused and set back like any other.
_SLIDER_BOX_DISABLED_CSS = (
    "<style>"
    ".mantine-Slider-root:has([data-disabled]) + .mantine-NumberInput-root{cursor:not-allowed}"
    ".mantine-Slider-root:has([data-disabled]) + .mantine-NumberInput-root input{"
    "pointer-events:none;opacity:.6;"
    "background:var(--mantine-color-disabled,#f1f3f5);"
    "color:var(--mantine-color-disabled-color,#adb5bd)}"
    "</style>")


def show_slider_boxes_disabled(client) -> Any:
    """On this client's page only, show a disabled slider's number box disabled too.

    Relies on: the viser client's slider being a Mantine ``Slider`` whose track carries
    ``data-disabled``, followed by a Mantine ``NumberInput`` (their static class names),
    and ``add_html`` rendering its content as HTML. Not in :func:`check` (it is the
    browser's DOM): ``tests/server/test_browser_presenter.py`` pins it."""
    return client.gui.add_html(_SLIDER_BOX_DISABLED_CSS)


def background_loop(viewer) -> asyncio.AbstractEventLoop | None:
    """The event loop viser's WebSocket server runs in (its own thread); None before
    the server has started.

    Relies on: ``WebsockServer._background_event_loop``."""
    try:
        return websocket_server(viewer)._background_event_loop
    except AttributeError as e:
        raise _missing("WebsockServer._background_event_loop", e) from e


def broadcast_buffer(viewer) -> Any:
    """The server's broadcast buffer (a ``viser.infra.AsyncMessageBuffer``): every
    message for all clients goes through it, its senders wait in :func:`background_loop`.

    Relies on: ``WebsockServer._broadcast_buffer`` (set when the server starts)."""
    try:
        return websocket_server(viewer)._broadcast_buffer
    except AttributeError as e:
        raise _missing("WebsockServer._broadcast_buffer", e) from e


def buffer_wakeup(buf) -> tuple[asyncio.Event, Any]:
    """``(event, loop)`` of one of viser's ``AsyncMessageBuffer``: its senders wait on
    ``event``; a message queued from another thread sets it through
    ``loop.call_soon_threadsafe(event.set)``.

    Relies on: ``AsyncMessageBuffer.message_event`` and ``.event_loop``."""
    try:
        return buf.message_event, buf.event_loop
    except AttributeError as e:
        raise _missing("AsyncMessageBuffer.message_event / .event_loop", e) from e


def set_buffer_wakeup(buf, event: asyncio.Event, loop) -> None:
    """Replace the event and the loop of :func:`buffer_wakeup` (before any sender
    waits on the old event).

    Relies on: ``AsyncMessageBuffer.message_event`` and ``.event_loop`` being read
    anew on every use (plain dataclass fields)."""
    buffer_wakeup(buf)    # both exist: fail clearly before changing either
    buf.message_event = event
    buf.event_loop = loop


def on_websocket_connect(viewer, cb: Callable) -> None:
    """Run ``cb(conn)`` (async or not) for every new viewer WebSocket, awaited before any
    message flows to it; ``conn.client_id`` is the client's id.

    Relies on: ``WebsockServer.on_client_connect``."""
    try:
        register = websocket_server(viewer).on_client_connect
    except AttributeError as e:
        raise _missing("WebsockServer.on_client_connect", e) from e
    register(cb)


def on_websocket_disconnect(viewer, cb: Callable) -> None:
    """Run ``cb(conn)`` (async or not) when a viewer WebSocket closes.

    Relies on: ``WebsockServer.on_client_disconnect``."""
    try:
        register = websocket_server(viewer).on_client_disconnect
    except AttributeError as e:
        raise _missing("WebsockServer.on_client_disconnect", e) from e
    register(cb)


def websocket_connection(viewer, client_id) -> Any:
    """The ``websockets`` server connection of a viewer client (its ``.request`` holds
    the HTTP upgrade's path and headers; ``await .close(code, reason)``), or None.

    Relies on: ``WebsockServer._live_connections`` (client id -> connection)."""
    try:
        return websocket_server(viewer)._live_connections.get(client_id)
    except AttributeError as e:
        raise _missing("WebsockServer._live_connections", e) from e


def wrap_incoming_handlers(viewer, message_cls: type, wrap: Callable) -> bool:
    """Replace every server-wide handler ``cb(client_id, message)`` viser registered for
    incoming messages of ``message_cls`` by ``wrap(cb)``. False if there was none.

    Relies on: ``WebsockServer._incoming_handlers`` (message class -> callbacks, read on
    every incoming message)."""
    try:
        table = websocket_server(viewer)._incoming_handlers
    except AttributeError as e:
        raise _missing("WebsockServer._incoming_handlers", e) from e
    handlers = table.get(message_cls)
    if not handlers:
        return False
    table[message_cls] = [wrap(cb) for cb in handlers]
    return True


def queue_to_client(client, message) -> None:
    """Send ``message`` to this one client (a ``viser.ClientHandle``) only.

    Relies on: ``ClientHandle._websock_connection.queue_message``."""
    try:
        conn = client._websock_connection
    except AttributeError as e:
        raise _missing("ClientHandle._websock_connection", e) from e
    conn.queue_message(message)


# ---------------------------------------------------------------- GUI handles

def gui_input_handles(viewer) -> list[tuple[str, Any]]:
    """``(uuid, handle)`` of every GUI input of the server's shared GUI (sliders,
    checkboxes, buttons, ...; removed ones may still be listed: :func:`is_removed`).

    Relies on: ``GuiApi._gui_input_handle_from_uuid``."""
    try:
        return list(viewer.gui._gui_input_handle_from_uuid.items())
    except AttributeError as e:
        raise _missing("GuiApi._gui_input_handle_from_uuid", e) from e


def gui_input_handle(viewer, uuid: str) -> Any:
    """The shared GUI's input handle of this uuid, or None.

    Relies on: ``GuiApi._gui_input_handle_from_uuid``."""
    try:
        return viewer.gui._gui_input_handle_from_uuid.get(uuid)
    except AttributeError as e:
        raise _missing("GuiApi._gui_input_handle_from_uuid", e) from e


def handle_value(handle) -> Any:
    """A GUI input's current value as the server holds it (what ``.value`` returns).

    Relies on: ``_GuiHandleState.value`` (``handle._impl``)."""
    try:
        return handle._impl.value
    except AttributeError as e:
        raise _missing("_GuiHandleState.value (a GUI handle's _impl)", e) from e


def handle_uuid(handle) -> str:
    """A GUI element's uuid (the id in its ``GuiUpdateMessage``).

    Relies on: ``_GuiHandleState.uuid`` (``handle._impl``)."""
    try:
        return handle._impl.uuid
    except AttributeError as e:
        raise _missing("_GuiHandleState.uuid (a GUI handle's _impl)", e) from e


def can_be_disabled(handle) -> bool:
    """Whether a GUI input has a ``disabled`` property (a progress bar, listed among the
    inputs for its value, has none: viser's client logs an error for an update of it).

    Relies on: ``_GuiHandleState.props`` (``handle._impl``), the element's props."""
    try:
        return hasattr(handle._impl.props, "disabled")
    except AttributeError as e:
        raise _missing("_GuiHandleState.props (a GUI handle's _impl)", e) from e


def is_removed(handle) -> bool:
    """Whether a GUI or scene handle was removed.

    Relies on: ``_GuiHandleState.removed`` / ``_SceneNodeHandleState.removed``
    (``handle._impl``)."""
    try:
        return handle._impl.removed
    except AttributeError as e:
        raise _missing("the handle state's .removed (a handle's _impl)", e) from e


def queue_update(handle, name: str, value) -> None:
    """Queue a handle's update of one property with ``value`` as it is (no cast, the
    handle's stored props untouched): a GUI handle sends a ``GuiUpdateMessage`` to
    every client, a scene node a ``SceneNodeUpdateMessage`` (owner-stamped).

    Relies on: ``AssignablePropsBase._queue_update(name, value)``."""
    try:
        queue = handle._queue_update
    except AttributeError as e:
        raise _missing(f"{type(handle).__name__}._queue_update", e) from e
    queue(name, value)


# ---------------------------------------------------------------- scene nodes

def stored_wxyz(handle) -> Any:
    """The scene node's own orientation array (float64, 4): the very array its public
    ``wxyz`` returns; written in place, later getter and setter calls see it.

    Relies on: ``_SceneNodeHandleState.wxyz`` (``handle._impl``)."""
    try:
        return handle._impl.wxyz
    except AttributeError as e:
        raise _missing("_SceneNodeHandleState.wxyz (a scene handle's _impl)", e) from e


def node_props(handle) -> Any:
    """The scene node's stored props (the message props object its property getters
    read; ``getattr``/``setattr`` by property name).

    Relies on: ``_SceneNodeHandleState.props`` (``handle._impl``)."""
    try:
        return handle._impl.props
    except AttributeError as e:
        raise _missing("_SceneNodeHandleState.props (a scene handle's _impl)", e) from e


def set_orientation_message(handle, wxyz: tuple) -> Any:
    """The ``SetOrientationMessage`` viser's ``wxyz`` setter sends for this node.

    Relies on: ``_SceneNodeHandleState.name`` and ``_messages.SetOrientationMessage``."""
    try:
        name = handle._impl.name
    except AttributeError as e:
        raise _missing("_SceneNodeHandleState.name (a scene handle's _impl)", e) from e
    if SetOrientationMessage is None:
        raise _missing("viser._messages.SetOrientationMessage")
    return SetOrientationMessage(name, wxyz)


def scene_update_message(handle, updates: dict) -> Any:
    """The ``SceneNodeUpdateMessage`` viser's property setters send for this node.

    Relies on: ``_SceneNodeHandleState.name`` and ``_messages.SceneNodeUpdateMessage``."""
    try:
        name = handle._impl.name
    except AttributeError as e:
        raise _missing("_SceneNodeHandleState.name (a scene handle's _impl)", e) from e
    if SceneNodeUpdateMessage is None:
        raise _missing("viser._messages.SceneNodeUpdateMessage")
    return SceneNodeUpdateMessage(name, updates)


def queue_scene_message(handle, message) -> None:
    """Queue a node's scene message the way viser's setters do (stamped with the node's
    scope owner: the server's, or one client's).

    Relies on: ``_SceneNodeHandleState.api`` and ``SceneApi._queue_scene_message``."""
    try:
        queue = handle._impl.api._queue_scene_message
    except AttributeError as e:
        raise _missing("SceneApi._queue_scene_message (a scene handle's _impl.api)", e) from e
    queue(message)


def after_prop_assigned(handle, name: str) -> None:
    """Run the node's hook viser calls after a property is assigned and queued (a mesh
    keeps related fields consistent).

    Relies on: ``AssignablePropsBase._on_prop_assigned``."""
    try:
        hook = handle._on_prop_assigned
    except AttributeError as e:
        raise _missing(f"{type(handle).__name__}._on_prop_assigned", e) from e
    hook(name)


# ---------------------------------------------------------------- start-up check

def _assigned_in(fn, attr: str) -> bool:
    """``fn``'s code names ``attr`` (an instance attribute it sets)."""
    code = getattr(fn, "__code__", None)
    return code is not None and attr in code.co_names


def _field(cls, name: str) -> bool:
    import dataclasses
    return dataclasses.is_dataclass(cls) and name in {f.name for f in dataclasses.fields(cls)}


def _probes() -> list[tuple[str, Callable[[], bool]]]:
    """(the internal, a check that it exists) for every internal above, from viser's
    classes (no server needed)."""
    def mod(path):
        import importlib
        return importlib.import_module(path)

    def gui_state():
        return mod("viser._gui_handles")._GuiHandleState

    def node_state():
        return mod("viser._scene_handles")._SceneNodeHandleState

    def infra():
        return mod("viser.infra._infra")

    def buffer():
        return mod("viser.infra._async_message_buffer").AsyncMessageBuffer

    probes = [(f"viser._messages.{n}", (lambda n=n: hasattr(_messages, n)))
              for n in ("GuiUpdateMessage", "SetOrientationMessage", "SceneNodeUpdateMessage",
                        "GuiBaseProps")]
    probes += [
        ("ViserServer._websock_server",
         lambda: _assigned_in(viser.ViserServer.__init__, "_websock_server")),
        ("WebsockServer._background_event_loop",
         lambda: any(_assigned_in(getattr(infra().WebsockServer, f), "_background_event_loop")
                     for f in ("__init__", "start"))),
        ("WebsockServer._broadcast_buffer",
         lambda: any(_assigned_in(getattr(infra().WebsockServer, f), "_broadcast_buffer")
                     for f in ("__init__", "start"))),
        ("WebsockServer.queue_message",
         lambda: callable(getattr(infra().WebsockServer, "queue_message", None))),
        ("GuiBaseProps.disabled", lambda: _field(_messages.GuiBaseProps, "disabled")),
        ("WebsockServer._live_connections",
         lambda: _assigned_in(infra().WebsockServer.__init__, "_live_connections")),
        ("WebsockServer._incoming_handlers",
         lambda: _assigned_in(infra().WebsockMessageHandler.__init__, "_incoming_handlers")),
        ("WebsockServer.on_client_connect",
         lambda: callable(getattr(infra().WebsockServer, "on_client_connect", None))),
        ("WebsockServer.on_client_disconnect",
         lambda: callable(getattr(infra().WebsockServer, "on_client_disconnect", None))),
        ("AsyncMessageBuffer.message_event", lambda: _field(buffer(), "message_event")),
        ("AsyncMessageBuffer.event_loop", lambda: _field(buffer(), "event_loop")),
        ("ClientHandle._websock_connection",
         lambda: _assigned_in(viser.ClientHandle.__init__, "_websock_connection")),
        ("WebsockClientConnection.queue_message",
         lambda: callable(getattr(infra().WebsockClientConnection, "queue_message", None))),
        ("GuiApi._gui_input_handle_from_uuid",
         lambda: _assigned_in(mod("viser._gui_api").GuiApi.__init__,
                              "_gui_input_handle_from_uuid")),
        ("_GuiHandleState.value", lambda: _field(gui_state(), "value")),
        ("_GuiHandleState.uuid", lambda: _field(gui_state(), "uuid")),
        ("_GuiHandleState.removed", lambda: _field(gui_state(), "removed")),
        ("GuiUplotHandle._queue_update",
         lambda: callable(getattr(viser.GuiUplotHandle, "_queue_update", None))),
        ("SceneNodeHandle._queue_update",
         lambda: callable(getattr(viser.SceneNodeHandle, "_queue_update", None))),
        ("SceneNodeHandle._on_prop_assigned",
         lambda: callable(getattr(viser.SceneNodeHandle, "_on_prop_assigned", None))),
        ("_SceneNodeHandleState.name", lambda: _field(node_state(), "name")),
        ("_SceneNodeHandleState.props", lambda: _field(node_state(), "props")),
        ("_SceneNodeHandleState.api", lambda: _field(node_state(), "api")),
        ("_SceneNodeHandleState.wxyz", lambda: _field(node_state(), "wxyz")),
        ("_SceneNodeHandleState.removed", lambda: _field(node_state(), "removed")),
        ("SceneApi._queue_scene_message",
         lambda: callable(getattr(mod("viser._scene_api").SceneApi, "_queue_scene_message",
                                  None))),
    ]
    return probes


def check(viewer=None) -> None:
    """Verify that every viser internal this module relies on exists in the installed
    viser; raise :class:`ViserInternalsError` naming every missing piece. With a
    running ``viser.ViserServer``, its live objects are checked too (the WebSocket
    server's attributes, the GUI's handle table). Call it at start-up, right after
    the ``ViserServer`` is made."""
    missing = []
    for piece, probe in _probes():
        try:
            ok = probe()
        except Exception:        # a module or class gone: the piece is missing
            ok = False
        if not ok:
            missing.append(piece)
    if viewer is not None:
        ws = getattr(viewer, "_websock_server", None)
        if ws is None:
            missing.append("ViserServer._websock_server (on the running server)")
        else:
            for attr in ("_background_event_loop", "_broadcast_buffer", "_live_connections",
                         "_incoming_handlers"):
                if not hasattr(ws, attr):
                    missing.append(f"WebsockServer.{attr} (on the running server)")
            buf = getattr(ws, "_broadcast_buffer", None)
            if buf is not None and not (hasattr(buf, "message_event")
                                        and hasattr(buf, "event_loop")):
                missing.append("AsyncMessageBuffer.message_event / .event_loop "
                               "(on the running server)")
        if not isinstance(getattr(getattr(viewer, "gui", None), "_gui_input_handle_from_uuid",
                                  None), dict):
            missing.append("GuiApi._gui_input_handle_from_uuid (on the running server)")
    if missing:
        raise ViserInternalsError(
            f"viser {getattr(viser, '__version__', '?')} lacks what orientlab relies on: "
            + ", ".join(missing) + " (app/server/viser_adapter.py is written for viser 1.1; "
            "adapt it, or install viser>=1.1,<1.2)")


__all__ = [
    "ViserInternalsError", "check", "GuiUpdateMessage", "SetOrientationMessage",
    "SceneNodeUpdateMessage", "message_classes", "gui_update_message", "websocket_server",
    "background_loop", "broadcast_buffer", "buffer_wakeup", "set_buffer_wakeup",
    "on_websocket_connect", "on_websocket_disconnect", "websocket_connection",
    "wrap_incoming_handlers", "queue_to_client", "gui_input_handles", "gui_input_handle",
    "handle_value", "handle_uuid", "can_be_disabled", "is_removed", "queue_update",
    "stored_wxyz", "node_props", "set_orientation_message", "scene_update_message", "queue_scene_message",
    "after_prop_assigned",
]
