"""How each phone app reaches this PC: the addresses of the Connect tab and
``GET /api/connect``, chosen well when the PC has several."""

from __future__ import annotations

import ipaddress
from typing import Any

from fastapi import Request

from app.server.net import lan_ipv4_all


def _ipv4(host: str | None) -> ipaddress.IPv4Address | None:
    try:
        return ipaddress.IPv4Address(host or "")
    except ValueError:
        return None


class Connect:
    """The addresses phones use (``settings``: the dashboard's ports)."""

    def __init__(self, settings, app_state):
        self.settings = settings
        self.st = app_state
        self.candidates = lan_ipv4_all()

    def host(self, request: Request | None = None) -> str:
        """The PC's address for phones: the one the page listens on when ``--host`` names
        one (a PC on several networks: the one picked); else the one the presenter's
        browser used, when it is a LAN address (it is then reachable from this network);
        else the best guess."""
        bound = _ipv4(self.settings.host)
        if bound is not None and not bound.is_unspecified and not bound.is_loopback:
            return str(bound)
        if request is not None:
            h = request.url.hostname
            ip = _ipv4(h)
            if ip is not None and not ip.is_loopback and not ip.is_unspecified:
                return h
        return self.candidates[0]

    def base_url(self, request: Request | None = None) -> str:
        return f"http://{self.host(request)}:{self.settings.port}"

    def unreachable(self) -> str | None:
        """Why phones cannot reach this PC (the page, or the Sensor Fusion app's port,
        listens on this PC only), or None."""
        def loopback(host: str | None) -> bool:
            host = (host or "").strip("[]")
            try:
                return host.lower() == "localhost" or ipaddress.ip_address(host).is_loopback
            except ValueError:
                return False

        page, tcp = loopback(self.settings.host), loopback(self.settings.phone_bind)
        if not (page or tcp):
            return None
        apps = ", ".join((["Sensor Logger", "phyphox"] if page else [])
                         + (["the Sensor Fusion app"] if tcp else []))
        where = self.settings.host if page else self.settings.phone_bind
        return (f"orientlab listens on {where.strip('[]')} only (--host): no phone can reach it "
                f"({apps}). Start orientlab without --host, or with --host set to this PC's "
                "network address.")

    def view(self, request: Request | None = None) -> dict[str, Any]:
        st = self.st
        base = self.base_url(request)
        return {
            "unreachable": self.unreachable(),
            "host": self.host(request), "other_hosts": [h for h in self.candidates
                                                        if h != self.host(request)],
            "sensor_logger": {"url": f"{base}/sensorlogger"},
            "phyphox": {"experiment_url": f"{base}/phyphox/orientlab.phyphox",
                        "push_url": f"{base}/phyphox"},
            "sensorfusion": {"host": self.host(request), "port": st.sensorfusion.port},
            "slot": st.slot.status(),
            "tcp": st.sensorfusion.status(),
            "http": st.http_phones.status(),
            "stream": self.stream_status(),
        }

    def stream_status(self) -> dict[str, Any]:
        """The stream on show: its app, rates, gaps and late samples, last data."""
        core = self.st.engine.core
        s = core.session
        if s is None:
            return {"kind": None}
        c = s.counts()
        rates = {k: (None if v != v else round(v, 1)) for k, v in s.rates().items()}
        return {"kind": s.kind, "app": s.phone_app or None, "label": s.label, "open": s.open,
                "close_reason": s.close_reason or None, "rates_hz": rates,
                "withheld": dict(s.withheld), "missing": s.missing(),
                "samples": c["samples"], "malformed": c["malformed"],
                "malformed_by_reason": c["malformed_by_reason"], "late": c["late"],
                "clamped": c["clamped"], "clock_offsets_s": s.clock_offsets,
                "last_sample_t": core.t_sent}
