"""``orientlab serve``: run the dashboard until Ctrl-C."""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import sys
import threading

import uvicorn

from app.config import ConfigError
from app.server.app import create_app
from app.server.limits import guarded_protocol, install_log_limits
from app.server.settings import Settings


def _quiet_cancelled(loop, context) -> None:
    """The loop's exception handler: a CancelledError reaching a callback is the end of a
    task at shutdown, not an error. (Python 3.11's ``asyncio.start_server`` calls
    ``task.exception()`` on its connection task when it is done: for a phone connection
    cancelled by Ctrl-C during a full-speed stream that raised CancelledError in the
    callback and printed a traceback.) Everything else goes to the default handler."""
    if isinstance(context.get("exception"), asyncio.CancelledError):
        logging.getLogger("orientlab").debug("a task was cancelled at shutdown: %s",
                                             context.get("message"))
        return
    loop.default_exception_handler(context)


class Server(uvicorn.Server):
    """uvicorn's server with :func:`_quiet_cancelled` on its event loop."""

    async def serve(self, sockets=None) -> None:
        asyncio.get_running_loop().set_exception_handler(_quiet_cancelled)
        await super().serve(sockets)


def make_server(settings: Settings, log_level: str = "warning") -> uvicorn.Server:
    """A uvicorn server for the dashboard (not started)."""
    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                            timeout_graceful_shutdown=0.5, ws_ping_interval=None,
                            # bounded resources (app/server/limits.py): a connection cap
                            # and one per address (a newcomer takes an idle connection's
                            # place, or a busy one of an address holding many), a
                            # first-byte and a header timeout, a minimum pace for request
                            # bodies, answers the client does not read and idle
                            # keep-alive connections closed
                            http=guarded_protocol(settings.max_connections,
                                                  settings.header_timeout_s,
                                                  settings.first_byte_timeout_s,
                                                  settings.max_connections_per_ip,
                                                  settings.min_body_bytes_per_s,
                                                  settings.write_stall_s,
                                                  app.state.access.presenter_host),
                            # uvicorn answers 503 when its connection table (idle ones
                            # included, and those closing) reaches this: above the cap
                            # the guard keeps, so it only bounds requests in flight
                            limit_concurrency=2 * settings.max_connections,
                            timeout_keep_alive=settings.keep_alive_s,
                            ws_max_size=1 << 16,
                            # /ws/state carries small JSON batches on a LAN: compressing
                            # them for every subscriber costs more CPU than it saves
                            ws_per_message_deflate=False)
    install_log_limits()   # after uvicorn has configured its loggers
    return Server(config)


#: the three listening ports: Settings attribute, the option that sets it
PORT_OPTIONS = (("port", "--port"), ("viewer_port", "--viewer-port"), ("phone_port", "--phone-port"))


class PortError(Exception):
    """A port that cannot be listened on; the message is the one line to show."""


def _bind_host(settings: Settings, attr: str) -> str:
    host = {"port": settings.host, "viewer_port": settings.viewer_bind,
            "phone_port": settings.phone_bind}[attr]
    return host or "0.0.0.0"


def _probe(host: str, port: int) -> None:
    """Bind (not listen) a socket as the real servers do (SO_REUSEADDR, so a port in
    TIME_WAIT is not mistaken for a taken one) and close it; OSError when taken."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(addr)


def check_ports(settings: Settings) -> None:
    """Raise :class:`PortError` naming the first of the three ports that is taken (or
    cannot be opened, or is given twice) and the option that changes it. Port 0 (any
    free port) is not checked. Viser would silently move to the next free port, the
    phone receiver and uvicorn would fail after the start-up: checking first gives one
    clear line before anything starts."""
    seen: dict[int, str] = {}
    for attr, opt in PORT_OPTIONS:
        port = int(getattr(settings, attr))
        if port == 0:
            continue
        if not 0 < port < 65536:
            raise PortError(f"port {port} ({opt}) is not a TCP port; choose one of 1-65535 "
                            f"with {opt} N")
        if port in seen:
            raise PortError(f"{seen[port]} and {opt} are both {port}; give each its own port "
                            f"(e.g. {opt} {port + 1})")
        seen[port] = opt
        host = _bind_host(settings, attr)
        try:
            _probe(host, port)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise PortError(f"port {port} ({opt}) is already in use; choose another "
                                f"with {opt} N") from None
            raise PortError(f"cannot listen on {host} port {port} ({opt}): "
                            f"{e.strerror or e}; choose another with {opt} N") from None


def raise_fd_limit(want: int = 8192) -> None:
    """Raise this process's open-file limit (soft, within the hard one) to ``want``: the
    viewer's server (viser) and the phone receiver have no connection cap of ours, and
    a desktop's default of 1024 descriptors is what one laptop's idle sockets would
    exhaust first (then every port stops accepting)."""
    try:
        import resource
    except ImportError:       # not on this system
        return
    try:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft == resource.RLIM_INFINITY or soft >= want:
            return
        new = want if hard == resource.RLIM_INFINITY else min(want, hard)
        if new > soft:
            resource.setrlimit(resource.RLIMIT_NOFILE, (new, hard))
    except (OSError, ValueError):
        pass


def serve(args) -> int:
    """Run with settings from ``args`` (host, port, viewer_port, phone_port, config,
    source). Returns the exit code: 0 after Ctrl-C, 2 for bad settings, 1 when a port
    cannot be opened (one line naming the port and its option, no traceback).

    The page answers at once: the filters are compiled (numba) in the background
    (:class:`app.warmup.Warmup`: it says so, one line per filter when it is ready;
    ``/api/health`` and the page say which are); the streams' samples wait until all
    are. A filter that cannot be compiled stops the server, exit status 1."""
    from app.warmup import Warmup

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    raise_fd_limit()
    logging.getLogger("orientlab").setLevel(logging.INFO)
    # the 3D viewer's websockets server says every viewer's connection at INFO: a class of
    # thirty is thirty lines in the teacher's terminal, none of them news
    logging.getLogger("websockets").setLevel(logging.WARNING)
    try:
        settings = Settings.from_args(args)
        check_ports(settings)
        server = make_server(settings)
    except PortError as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 1
    except (ConfigError, FileNotFoundError, ValueError) as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 2
    failed: list[str] = []

    def on_failure(text: str) -> None:   # from the warm-up's thread
        failed.append(text)
        server.should_exit = True

    warmup = Warmup(prog="orientlab serve", on_failure=on_failure,
                    note="the page answers meanwhile and says which filters are ready")
    server.config.app.state.warmup = warmup    # the lifespan, /api/health

    def start_when_serving() -> None:
        # the server's start-up (imports, the 3D scene's few compiled helpers) first:
        # the page answers sooner, the filters follow a moment later
        while not server.started and not warmup.done.wait(0.05):
            if server.should_exit:
                return
        warmup.start()

    threading.Thread(target=start_when_serving, name="orientlab-warmup-start", daemon=True).start()
    try:
        server.run()
    except SystemExit as e:  # uvicorn exits when it cannot bind its port
        return int(e.code or 1)
    except OSError as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 1
    finally:
        warmup.stop()
    return 0 if server.started and not failed else 1
