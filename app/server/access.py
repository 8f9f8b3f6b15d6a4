"""Who may change the session: the presenter's token, and Origin checks.

A classroom network is hostile (a stray script, a classmate's browser tab): anyone on
it may *watch*, only the presenter may *change* the session.

- **The token.** At start a random token is made (``secrets.token_urlsafe``) unless the
  settings give one, and printed in the presenter's link (``http://HOST:PORT/?token=...``,
  as Jupyter does). Opening that link stores the token in a cookie (``HttpOnly``,
  ``SameSite=Strict``), so the page, the API docs' "Try it out" and the viewer embedded
  in the page act as the presenter. A script sends it as ``X-Orientlab-Token: ...`` or
  ``Authorization: Bearer ...`` (``?token=...`` in the URL works too).
- **Without the token** the page and the 3D viewer are watch-only: the viewer's
  controls are shown disabled and any change a viewer sends is refused (the control is
  set back), and every changing API call answers **403**.
- ``--open`` (``Settings.open_access``) turns the token off, for a trusted network.
- **Origin.** A browser names the page a request comes from. A state-changing request
  or a WebSocket (``/ws/state`` and the viewer's) whose ``Origin`` is not this server
  (same host name) is refused, token or not: a cross-site form post or a foreign page's
  script cannot reset the filters or listen in. Requests without ``Origin`` (scripts,
  curl) are judged by the token alone.

**For routers:** every state-changing route takes the one dependency
:func:`require_presenter`::

    from ..access import require_presenter
    router = APIRouter(dependencies=[Depends(require_presenter)])   # every route
    @router.post("/api/thing", dependencies=[Depends(require_presenter)])  # or one route

It answers 403 (with the reason) unless the request carries the token (or the server
runs with ``--open``) and comes from an acceptable Origin.

The viewer (viser) is guarded by :func:`guard_viewer`: it reads the token from the
viewer's WebSocket URL (the page embeds ``?websocket=ws://HOST:VPORT/?token=...``),
closes WebSockets from a foreign Origin, and drops every GUI input (value changes,
button clicks, uploads) from a client without the token.
"""

from __future__ import annotations

import inspect
import logging
import secrets
import threading
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

from fastapi import HTTPException, Request, WebSocket

log = logging.getLogger("orientlab.access")

COOKIE = "orientlab_token"
HEADER = "x-orientlab-token"


def _host_of(url_or_host: str | None) -> str | None:
    """The lower-case host name of an ``Origin`` (``http://a.b:8000``) or a ``Host``
    header (``a.b:8000``, ``[::1]:8000``)."""
    if not url_or_host:
        return None
    s = url_or_host.strip()
    if "://" not in s:
        s = "//" + s
    try:
        h = urlsplit(s).hostname
    except ValueError:
        return None
    return h.lower() if h else None


@dataclass
class Access:
    """The session's access rules (one per server, on ``app.state.access``)."""
    token: str
    open: bool = False
    presenters: set = field(default_factory=set)      # viser client ids holding the token
    lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def from_settings(cls, settings) -> "Access":
        tok = getattr(settings, "token", None) or secrets.token_urlsafe(18)
        return cls(token=tok, open=bool(getattr(settings, "open_access", False)))

    # ------------------------------------------------------------ checks
    def token_ok(self, candidate: str | None) -> bool:
        if self.open:
            return True
        if not candidate:
            return False
        return secrets.compare_digest(candidate.encode(), self.token.encode())

    @staticmethod
    def origin_ok(origin: str | None, host: str | None) -> bool:
        """No Origin (not a browser) or an Origin on this server's host name."""
        if origin is None:
            return True
        if origin == "null":   # sandboxed frame, file:// page: never this server's page
            return False
        o, h = _host_of(origin), _host_of(host)
        return o is not None and h is not None and o == h

    def token_of(self, conn: Request | WebSocket) -> str | None:
        h = conn.headers
        tok = h.get(HEADER)
        if not tok:
            auth = h.get("authorization", "")
            if auth.lower().startswith("bearer "):
                tok = auth[7:].strip()
        return tok or conn.query_params.get("token") or conn.cookies.get(COOKIE)

    def is_presenter(self, conn: Request | WebSocket) -> bool:
        return self.token_ok(self.token_of(conn))

    def presenter_link(self, base: str) -> str:
        return base if self.open else f"{base}?token={self.token}"

    # ------------------------------------------------------------ viewer (viser)
    def viewer_allowed(self, client_id) -> bool:
        if self.open:
            return True
        with self.lock:
            return client_id in self.presenters


async def require_presenter(request: Request) -> None:
    """FastAPI dependency for every state-changing route: 403 unless the request comes
    from an acceptable Origin and carries the presenter's token (or ``--open``). Async:
    a plain ``def`` dependency would run in FastAPI's thread pool, a thread hop per
    request."""
    acc: Access = request.app.state.access
    if not acc.origin_ok(request.headers.get("origin"), request.headers.get("host")):
        raise HTTPException(403, "refused: this request comes from another site (Origin "
                                 "is not this server)")
    if not acc.is_presenter(request):
        raise HTTPException(403, "refused: only the presenter may change the session "
                                 "(open the presenter's link printed at start, or send "
                                 "the token as X-Orientlab-Token)")


async def phone_push(request: Request) -> None:
    """FastAPI dependency that marks a route a phone app calls (Sensor Logger's and
    phyphox's pushes): no token (a phone has none) and no Origin (an app sends none); who
    may stream is decided by the phone slot (:mod:`app.sources.slot`), and what a push
    may do is only that: add samples to the stream on show."""
    return None


async def require_presenter_read(request: Request) -> None:
    """FastAPI dependency for what only the presenter may *see* (the addresses phones
    connect to, their QR codes): 403 unless the request carries the token (or
    ``--open``); no Origin check (reading changes nothing)."""
    acc: Access = request.app.state.access
    if not acc.is_presenter(request):
        raise HTTPException(403, "refused: only the presenter sees how phones connect "
                                 "(open the presenter's link printed at start)")


def websocket_origin_ok(ws: WebSocket) -> bool:
    acc: Access = ws.app.state.access
    return acc.origin_ok(ws.headers.get("origin"), ws.headers.get("host"))


# ---------------------------------------------------------------- the viewer

def _viewer_inputs():
    """viser's client -> server message classes that change something (everything a
    watcher must not send). Camera moves and the scene pointer stay free (per client)."""
    from app.server import viser_adapter as va
    names = ("GuiUpdateMessage", "GuiButtonHoldMessage", "GuiFormSubmitMessage",
             "GuiFormDirtyMessage", "FileTransferStartUpload", "FileTransferPart",
             "CommandTriggerMessage", "SceneNodeClickMessage", "ShareUrlRequest",
             "ShareUrlDisconnect")
    return va.message_classes(names)


def guard_viewer(viewer, access: Access, after_refusal=None) -> None:
    """Put the presenter rule on a running ``viser.ViserServer`` (see the module doc).

    Relies on viser's WebSocket server (a connection's upgrade request, the incoming
    message handlers) through :mod:`app.server.viser_adapter`; checked by
    tests/server/test_faults.py."""
    from app.server import viser_adapter as va

    async def _check(conn) -> None:   # awaited before any message flows to the client
        live = va.websocket_connection(viewer, conn.client_id)
        req = getattr(live, "request", None)
        headers = req.headers if req is not None else {}
        if not access.origin_ok(headers.get("Origin"), headers.get("Host")):
            log.warning("viewer: refused a WebSocket from Origin %.80s", headers.get("Origin"))
            await live.close(1008, "foreign Origin")
            return
        query = parse_qs(urlsplit(req.path).query) if req is not None else {}
        tok = (query.get("token") or [None])[0]
        if access.token_ok(tok):
            with access.lock:
                access.presenters.add(conn.client_id)

    va.on_websocket_connect(viewer, _check)

    async def _gone(conn) -> None:
        with access.lock:
            access.presenters.discard(conn.client_id)

    va.on_websocket_disconnect(viewer, _gone)

    gui_update = None
    for cls in _viewer_inputs():
        if cls.__name__ == "GuiUpdateMessage":
            gui_update = cls
        va.wrap_incoming_handlers(
            viewer, cls,
            lambda cb, cls=cls, gui_update=gui_update: _guarded(cb, cls, viewer, access,
                                                                gui_update, after_refusal))

    @viewer.on_client_connect
    def _watch_only(client) -> None:
        if access.viewer_allowed(client.client_id):
            return
        client.add_notification("Watch-only", "Only the presenter can change the session "
                                "(the presenter's link holds a token).", color="blue",
                                auto_close_seconds=8.0)
        _disable_controls(viewer, client)
        # the GUI's own messages may still be on their way to this client: say it again
        loop = va.background_loop(viewer)
        if loop is not None:
            for delay in (1.0, 4.0):
                loop.call_later(delay, _disable_controls, viewer, client)


def _disable_controls(viewer, client) -> None:
    """Show every input control disabled, to this client only."""
    from app.server import viser_adapter as va
    if client.client_id not in viewer.get_clients():
        return   # gone meanwhile
    try:
        handles = va.gui_input_handles(viewer)
        with client.atomic():
            for uuid, h in handles:
                if not va.is_removed(h):
                    va.queue_to_client(client, va.gui_update_message(uuid, {"disabled": True}))
    except Exception:  # a client gone meanwhile
        log.debug("could not disable a viewer's controls", exc_info=True)


def _guarded(cb, cls, viewer, access: Access, gui_update, after_refusal):
    """``cb`` run only for presenter clients; a refused GUI change is set back on the
    client that sent it."""
    from app.server import viser_adapter as va

    def refuse(client_id, message) -> None:
        log.info("viewer: refused %s from a watch-only client", cls.__name__)
        if gui_update is not None and isinstance(message, gui_update):
            client = viewer.get_clients().get(client_id)
            h = va.gui_input_handle(viewer, message.uuid)
            if client is not None and h is not None and "value" in message.updates:
                va.queue_to_client(client, gui_update(message.uuid, {"value": va.handle_value(h),
                                                                     "disabled": True}))
        if after_refusal is not None:
            after_refusal(client_id)

    if inspect.iscoroutinefunction(cb):
        async def guarded(client_id, message):
            if not access.viewer_allowed(client_id):
                return refuse(client_id, message)
            return await cb(client_id, message)
    else:
        def guarded(client_id, message):
            if not access.viewer_allowed(client_id):
                return refuse(client_id, message)
            return cb(client_id, message)
    return guarded


__all__ = ["Access", "require_presenter", "websocket_origin_ok", "guard_viewer", "COOKIE",
           "HEADER"]
