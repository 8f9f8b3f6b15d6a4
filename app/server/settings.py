"""The dashboard's settings: one typed object, built from the command line."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path


def user_preset_dir() -> Path:
    """Where presets saved from the dashboard go: ``$ORIENTLAB_PRESETS``, else
    ``$XDG_DATA_HOME/orientlab/presets`` (``~/.local/share/orientlab/presets``); never
    the source tree (the shipped presets in ``configs/`` are read-only)."""
    env = os.environ.get("ORIENTLAB_PRESETS")
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "orientlab" / "presets"


@dataclass(frozen=True)
class Settings:
    """Everything ``orientlab serve`` can be told (see ``orientlab serve --help``).

    ``source`` is ``"demo"`` (the built-in simulated phone), ``"none"`` (wait for a
    phone), ``"phyphox:http://PHONE:PORT"`` (poll a phyphox phone's remote access) or the
    path of a Sensor Fusion app log replayed at real-time speed in a loop.
    """
    host: str = "0.0.0.0"            # HTTP page and API
    port: int = 8000
    viewer_host: str | None = None   # viser; None: same as host
    viewer_port: int = 8080
    phone_host: str | None = None    # phone receiver; None: same as host
    phone_port: int = 3400
    source: str = "demo"
    recordings: Path = Path("recordings")   # --recordings: the lab's recordings folder
    # a recording stops cleanly at any of these (app/toolkit/recording.py RecordingLimits);
    # None or 0 turns one off
    recording_max_s: float | None = 3600.0          # duration cap (wall time)
    recording_max_bytes: int | None = 500_000_000   # size cap (every segment's files)
    recording_min_free_bytes: int | None = 200_000_000   # stops below this much free disk
    recording_estimates_hz: float = 20.0   # estimates rows/s per estimator (0: every sample);
                                           # the full rate: `orientlab estimate` on the log
    recording_gzip: bool = True            # the estimates as .estimates.csv.gz
    config: str | None = None        # a preset file or name (configs/<name>.toml)
    preset_dir: Path = field(default_factory=user_preset_dir)   # saved presets (user folder)
    max_presets: int = 200           # saving more is refused
    # access (see app/server/access.py)
    open_access: bool = False        # --open: no token, anyone may change the session
    token: str | None = None         # the presenter's token; None: a random one at start
    # resources
    max_body_bytes: int = 1 << 20    # a longer HTTP request body is answered 413
    max_push_bytes: int = 16 << 20   # likewise for a phone's push (a long batch of a fast phone)
    max_connections: int = 200       # HTTP connections at once; more are closed at once
    header_timeout_s: float = 10.0   # a request's headers must arrive within this
    first_byte_timeout_s: float = 2.5   # a connection that sends nothing is closed after this
                                     # (a browser sends its request within milliseconds)
    max_connections_per_ip: int = 32  # HTTP connections (and WebSockets) of one address: a
                                     # browser opens ~6 per host and one per WebSocket
    keep_alive_s: int = 5            # an idle HTTP connection is closed after this
    min_body_bytes_per_s: float = 1000.0   # a request body slower than this (judged over
                                     # header_timeout_s) is closed; 0: off
    write_stall_s: float = 30.0      # an answer the client does not read for this long is
                                     # closed; 0: off
    phone_hello_s: float = 3.0       # a phone must send a valid sample within this
    # receiver
    max_line_bytes: int = 65536      # a longer line without newline closes the connection
    phone_idle_s: float = 3.0        # a second phone may take over after this much silence
    reorder_window_s: float = 0.05   # SampleOrderer window
    # sources
    demo_seed: int = 0
    replay_pause_s: float = 1.0      # pause between two loops of a replayed log
    # display
    plot_hz: float = 2.0             # plots: each refresh resends every chart whole to every viewer
    text_hz: float = 5.0             # the indicators (pills, 3D label); the status line and the
                                     # read-outs go with the plots (sent only when changed)
    scene_hz: float = 20.0           # cones, arrows, other phones (the primary's pose: every batch)
    ws_hz: float = 10.0              # WS /ws/state messages (each holds every estimate since the last)
    history_s: float = 20.0
    verbose: bool = True             # print the start-up banner

    @property
    def phyphox_url(self) -> str | None:
        """The phone polled with ``--source phyphox:URL``, else None."""
        return self.source[len("phyphox:"):] if self.source.startswith("phyphox:") else None

    @property
    def viewer_bind(self) -> str:
        return self.viewer_host or self.host

    @property
    def phone_bind(self) -> str:
        return self.phone_host or self.host

    @classmethod
    def from_args(cls, args) -> "Settings":
        """From an argparse namespace with host, port, viewer_port, phone_port, config, source."""
        kw = {}
        for name in ("host", "port", "viewer_port", "phone_port", "config", "source", "recordings"):
            v = getattr(args, name, None)
            if v is not None:
                kw[name] = str(v) if name in ("config", "source") else (Path(v) if name == "recordings" else v)
        if getattr(args, "open", False):
            kw["open_access"] = True
        if getattr(args, "presets_dir", None):
            kw["preset_dir"] = Path(args.presets_dir).expanduser()
        return cls(**kw)
