"""``orientlab serve``: run the dashboard until Ctrl-C."""

from __future__ import annotations

import errno
import logging
import socket
import sys

import uvicorn

from app.config import ConfigError
from app.server.app import create_app
from app.server.limits import guarded_protocol, install_log_limits
from app.server.settings import Settings


def make_server(settings: Settings, log_level: str = "warning") -> uvicorn.Server:
    """A uvicorn server for the dashboard (not started)."""
    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                            timeout_graceful_shutdown=0.5, ws_ping_interval=None,
                            # bounded resources (app/server/limits.py): a connection cap,
                            # a header timeout, idle keep-alive connections closed
                            http=guarded_protocol(settings.max_connections,
                                                  settings.header_timeout_s),
                            limit_concurrency=settings.max_connections,
                            timeout_keep_alive=settings.keep_alive_s,
                            ws_max_size=1 << 16,
                            # /ws/state carries small JSON batches on a LAN: compressing
                            # them for every subscriber costs more CPU than it saves
                            ws_per_message_deflate=False)
    install_log_limits()   # after uvicorn has configured its loggers
    return uvicorn.Server(config)


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


def serve(args) -> int:
    """Run with settings from ``args`` (host, port, viewer_port, phone_port, config,
    source). Returns the exit code: 0 after Ctrl-C, 2 for bad settings, 1 when a port
    cannot be opened (one line naming the port and its option, no traceback).

    The ports are checked before and again after the filters are compiled (numba,
    :func:`app.warmup.prepare`: it says so when that takes more than a moment)."""
    from app.warmup import prepare

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("orientlab").setLevel(logging.INFO)
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
    prepare(prog="orientlab serve")
    try:
        check_ports(settings)   # taken while numba compiled?
    except PortError as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 1
    try:
        server.run()
    except SystemExit as e:  # uvicorn exits when it cannot bind its port
        return int(e.code or 1)
    except OSError as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 1
    return 0 if server.started else 1
