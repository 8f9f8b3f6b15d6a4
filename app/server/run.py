"""``orientlab serve``: run the dashboard until Ctrl-C."""

from __future__ import annotations

import logging
import sys

import uvicorn

from ..config import ConfigError
from .app import create_app
from .settings import Settings


def make_server(settings: Settings, log_level: str = "warning") -> uvicorn.Server:
    """A uvicorn server for the dashboard (not started)."""
    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level=log_level,
                            timeout_graceful_shutdown=0.5, ws_ping_interval=None,
                            # /ws/state carries small JSON batches on a LAN: compressing
                            # them for every subscriber costs more CPU than it saves
                            ws_per_message_deflate=False)
    return uvicorn.Server(config)


def serve(args) -> int:
    """Run with settings from ``args`` (host, port, viewer_port, phone_port, config,
    source). Returns the exit code: 0 after Ctrl-C, 2 for bad settings, 1 when a port
    cannot be opened."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("orientlab").setLevel(logging.INFO)
    try:
        settings = Settings.from_args(args)
        server = make_server(settings)
    except (ConfigError, FileNotFoundError, ValueError) as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 2
    try:
        server.run()
    except SystemExit as e:  # uvicorn exits when it cannot bind its port
        return int(e.code or 1)
    except OSError as e:
        print(f"orientlab serve: {e}", file=sys.stderr)
        return 1
    return 0 if server.started else 1
