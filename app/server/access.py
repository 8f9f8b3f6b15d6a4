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
  controls are shown disabled (also one enabled later for everyone, such as an "apply"
  button after the presenter's fit), any change a viewer sends is refused (the control
  is set back), and every changing API call answers **403**.
- ``--open`` (``Settings.open_access``) turns the token off, for a trusted network.
- **Origin.** A browser names the page a request comes from. A state-changing request
  or a WebSocket (``/ws/state`` and the viewer's) whose ``Origin`` is not a page of this
  server is refused, token or not: a cross-site form post or a foreign page's script
  cannot reset the filters or listen in. "This server" is scheme, host and port: the
  scheme the request came in with, a host name of this machine (``localhost``, a
  loopback address, one of its own addresses or its host name; never what the request
  says it is) and one of this server's ports (the HTTP and the viewer port, as
  configured or bound). Another app on another port of the same PC is another site.
  Requests without ``Origin`` (scripts, curl) are judged by the token alone.
- **Host (DNS rebinding).** A state-changing request whose ``Host`` names another host
  (``evil.example`` resolved to this PC's address by a foreign page's DNS) is refused:
  only this machine's names and addresses are accepted, so the presenter's page on
  ``http://localhost:PORT``, ``http://127.0.0.1:PORT`` and ``http://<LAN IP>:PORT``
  works and a rebound name does not.

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

import contextlib
import inspect
import ipaddress
import logging
import secrets
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from http.cookies import SimpleCookie
from urllib.parse import parse_qs, urlsplit

from fastapi import HTTPException, Request, WebSocket

log = logging.getLogger("orientlab.access")

COOKIE = "orientlab_token"
PRESENTER_HOSTS_KEPT = 4     # the presenter's latest addresses kept (Access.presenter_host)
HEADER = "x-orientlab-token"


def printable(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters, each one a terminal would act on (ESC, a
    backspace, a right-to-left override: a path a client chose) written as an escape."""
    text = text[:limit]
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii")
                   for c in text)


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


def _split_origin(origin: str) -> tuple[str, str, int] | None:
    """``(scheme, host, port)`` of an ``Origin`` (the port made explicit), else None."""
    try:
        u = urlsplit(origin.strip())
        port = u.port
    except ValueError:
        return None
    scheme = (u.scheme or "").lower()
    if scheme not in ("http", "https") or not u.hostname:
        return None
    return scheme, u.hostname.lower(), port if port is not None else (443 if scheme == "https" else 80)


_OWN_TTL_S = 30.0          # this machine's addresses, looked up again after this (DHCP)


def _own_names() -> frozenset:
    """This machine's host names and addresses (no traffic: the host name and the
    interfaces' addresses). :meth:`Access.own_names` caches them for a while."""
    names = {"localhost", "localhost.localdomain", "ip6-localhost"}
    try:
        hn = socket.gethostname().lower()
        if hn:
            names |= {hn, hn.split(".")[0] + ".local"}
    except OSError:
        pass
    try:
        from app.server.net import lan_ipv4_all
        names |= set(lan_ipv4_all())
    except Exception:     # an odd network set-up: loopback still works
        log.debug("could not list this machine's addresses", exc_info=True)
    return frozenset(names)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass
class Access:
    """The session's access rules (one per server, on ``app.state.access``)."""
    token: str
    open: bool = False
    presenters: set = field(default_factory=set)      # viser client ids holding the token
    lock: threading.Lock = field(default_factory=threading.Lock)
    ports: frozenset = frozenset()     # this server's HTTP and viewer ports (as configured)
    hosts: frozenset = frozenset()     # the addresses it is configured to listen on
    # this machine's names and addresses, and when they were looked up (own_names)
    _own: tuple = field(default=(float("-inf"), frozenset()), repr=False)
    _own_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    # changing requests refused, by reason (GET /api/stats "access_refused"; each logged)
    refused: Counter = field(default_factory=Counter, repr=False)
    # the addresses the presenter's token came from lately, the latest last: the connection
    # guard never takes their connections for another address's (app.server.limits)
    _presenter_hosts: dict = field(default_factory=dict, repr=False)

    def refuse(self, request: Request, reason: str, detail: str) -> HTTPException:
        """Count and log a refused request (``reason``: host, origin, no_token,
        wrong_token); the 403 to raise. The log line names the route and the client's
        address, never the token tried."""
        with self.lock:
            self.refused[reason] += 1
        client = request.client.host if request.client else "?"
        log.warning("refused %s %s from %s: %s", request.method, printable(request.url.path, 80),
                    client, reason.replace("_", " "))
        return HTTPException(403, detail)

    @classmethod
    def from_settings(cls, settings) -> "Access":
        tok = getattr(settings, "token", None) or secrets.token_urlsafe(18)
        ports = {int(p) for p in (getattr(settings, "port", 0), getattr(settings, "viewer_port", 0))
                 if p}
        hosts = {str(h).lower() for h in (getattr(settings, "host", None),
                                          getattr(settings, "viewer_host", None))
                 if h and str(h) not in ("0.0.0.0", "::", "")}
        return cls(token=tok, open=bool(getattr(settings, "open_access", False)),
                   ports=frozenset(ports), hosts=frozenset(hosts))

    def own_host(self, host: str | None, local: str | None = None) -> bool:
        """A host name (of an Origin or a Host header, no port) naming this machine:
        ``localhost``, a loopback address, the address the connection came in on
        (``local``), a configured listening address, one of its addresses or its host
        name. Never a name only the request vouches for (DNS rebinding)."""
        if not host:
            return False
        h = host.lower().strip("[]")
        if _is_loopback(h) or h in self.hosts:
            return True
        if local is not None and h == str(local).lower().strip("[]"):
            return True
        return h in self.own_names()

    def own_names(self) -> frozenset:
        """This machine's host names and addresses, looked up again after ``_OWN_TTL_S``
        (a laptop's DHCP address changes mid-lesson)."""
        now = time.monotonic()
        with self._own_lock:
            at, names = self._own
        if now - at < _OWN_TTL_S:
            return names
        names = _own_names()
        with self._own_lock:
            self._own = (now, names)
        return names

    def host_ok(self, host_header: str | None, local: str | None = None) -> bool:
        """The ``Host`` header of a state-changing request: absent (HTTP/1.0, a bare
        script) or naming this machine (:meth:`own_host`)."""
        if host_header is None:
            return True
        return self.own_host(_host_of(host_header), local)

    # ------------------------------------------------------------ checks
    def token_ok(self, candidate: str | None) -> bool:
        if self.open:
            return True
        if not candidate:
            return False
        return secrets.compare_digest(candidate.encode(), self.token.encode())

    def origin_ok(self, origin: str | None, host: str | None = None,
                  local: tuple | None = None, scheme: str = "http") -> bool:
        """No Origin (not a browser), or an Origin that is a page of this server: the
        request's ``scheme`` (``http``/``https``), a host of this machine
        (:meth:`own_host`) and one of this server's ports (configured, or ``local``:
        the ``(address, port)`` the connection came in on). ``host`` (the Host header)
        is not trusted for it (DNS rebinding); see :meth:`host_ok`."""
        if origin is None:
            return True
        if origin == "null":   # sandboxed frame, file:// page: never this server's page
            return False
        parts = _split_origin(origin)
        if parts is None:
            return False
        o_scheme, o_host, o_port = parts
        want = {"ws": "http", "wss": "https"}.get(scheme, scheme)
        if o_scheme != want:
            return False
        local_addr, local_port = (local[0], local[1]) if local else (None, None)
        ports = set(self.ports)
        if local_port:
            ports.add(int(local_port))
        if o_port not in ports:
            return False
        return self.own_host(o_host, local_addr)

    def token_of(self, conn: Request | WebSocket) -> str | None:
        h = conn.headers
        tok = h.get(HEADER)
        if not tok:
            auth = h.get("authorization", "")
            if auth.lower().startswith("bearer "):
                tok = auth[7:].strip()
        return tok or conn.query_params.get("token") or conn.cookies.get(COOKIE)

    def is_presenter(self, conn: Request | WebSocket) -> bool:
        ok = self.token_ok(self.token_of(conn))
        if ok and not self.open and conn.client is not None:
            host = conn.client.host
            with self.lock:
                self._presenter_hosts.pop(host, None)
                self._presenter_hosts[host] = None
                while len(self._presenter_hosts) > PRESENTER_HOSTS_KEPT:
                    del self._presenter_hosts[next(iter(self._presenter_hosts))]
        return ok

    def presenter_host(self, host: str) -> bool:
        """Whether the presenter's token came from this address lately (never with
        ``--open``, where everyone may change the session)."""
        return host in self._presenter_hosts

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
    local = request.scope.get("server")
    if not acc.host_ok(request.headers.get("host"), local[0] if local else None):
        raise acc.refuse(request, "host", "refused: this request names another host (Host "
                                          "is not an address of this server)")
    if not acc.origin_ok(request.headers.get("origin"), request.headers.get("host"), local,
                         request.url.scheme):
        raise acc.refuse(request, "origin", "refused: this request comes from another site "
                                            "(Origin is not this server)")
    if not acc.is_presenter(request):
        raise acc.refuse(request, "wrong_token" if acc.token_of(request) else "no_token",
                         "refused: only the presenter may change the session (open the "
                         "presenter's link printed at start, or send the token as "
                         "X-Orientlab-Token)")


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
    return acc.origin_ok(ws.headers.get("origin"), ws.headers.get("host"),
                         ws.scope.get("server"), ws.url.scheme)


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

    refused: set = set()    # connections closed for their Origin: never greeted

    async def _check(conn) -> None:   # awaited before any message flows to the client
        live = va.websocket_connection(viewer, conn.client_id)
        req = getattr(live, "request", None)
        headers = req.headers if req is not None else {}
        if not access.origin_ok(headers.get("Origin"), headers.get("Host"),
                                getattr(live, "local_address", None)):
            log.warning("viewer: refused a WebSocket from Origin %.80s", headers.get("Origin"))
            with access.lock:
                refused.add(conn.client_id)
            await live.close(1008, "foreign Origin")
            return
        query = parse_qs(urlsplit(req.path).query) if req is not None else {}
        tok = (query.get("token") or [None])[0]
        if tok is None:
            # the presenter's cookie (a cookie is the host's, whatever its port): the page's
            # viewer, and the viewer opened in its own tab, need no token in their address
            jar = SimpleCookie()
            with contextlib.suppress(Exception):
                jar.load(headers.get("Cookie") or "")
            tok = jar[COOKIE].value if COOKIE in jar else None
        if access.token_ok(tok):
            with access.lock:
                access.presenters.add(conn.client_id)

    va.on_websocket_connect(viewer, _check)

    async def _gone(conn) -> None:
        with access.lock:
            access.presenters.discard(conn.client_id)
            refused.discard(conn.client_id)

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
        with access.lock:
            gone = client.client_id in refused or client.client_id not in viewer.get_clients()
        if gone:
            return   # refused for its Origin (closed, maybe not yet unregistered), or gone
        client.add_notification("Watch-only", "Only the presenter can change the session "
                                "(the presenter's link holds a token).", color="blue",
                                auto_close_seconds=8.0)
        _disable_controls(viewer, client)
        va.show_slider_boxes_disabled(client)
        # the GUI's own messages may still be on their way to this client: say it again
        loop = va.background_loop(viewer)
        if loop is not None:
            for delay in (1.0, 4.0):
                loop.call_later(delay, _disable_controls, viewer, client)

    def _keep_disabled(message) -> None:
        """A control enabled later (an "apply" button after a fit, an input added) is
        enabled for every client: show it disabled again to the watch-only ones."""
        uuid = va.enabled_input(message)
        if uuid is None:
            return
        loop = va.background_loop(viewer)
        if loop is None:
            return
        # the broadcast and a client's own messages leave on two queues, in no fixed
        # order: say it after the broadcast has gone out, and once more
        for delay in KEEP_DISABLED_AFTER_S:
            loop.call_soon_threadsafe(loop.call_later, delay, _disable_for_watchers,
                                      viewer, access, uuid)

    va.on_broadcast(viewer, _keep_disabled)


# seconds after a control is enabled for all when the watch-only clients are told it is not
KEEP_DISABLED_AFTER_S = (0.2, 1.0)


def _shown_disabled(handle) -> bool:
    """Whether a GUI input is one a watch-only client is shown disabled: still there, and
    with a ``disabled`` property (viser lists progress bars among the inputs too)."""
    from app.server import viser_adapter as va
    return not va.is_removed(handle) and va.can_be_disabled(handle)


def _disable_for_watchers(viewer, access: Access, uuid: str) -> None:
    """Show the input ``uuid`` disabled to every watch-only client (on viser's loop)."""
    from app.server import viser_adapter as va
    h = va.gui_input_handle(viewer, uuid)
    if h is None or not _shown_disabled(h):
        return
    for client_id, client in viewer.get_clients().items():
        if access.viewer_allowed(client_id):
            continue
        try:
            va.queue_to_client(client, va.gui_update_message(uuid, {"disabled": True}))
        except Exception:  # a client gone meanwhile
            log.debug("could not disable a viewer's control", exc_info=True)


def _disable_controls(viewer, client) -> None:
    """Show every input control disabled, to this client only."""
    from app.server import viser_adapter as va
    if client.client_id not in viewer.get_clients():
        return   # gone meanwhile
    try:
        handles = va.gui_input_handles(viewer)
        with client.atomic():
            for uuid, h in handles:
                if _shown_disabled(h):
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
