"""The PC's LAN IPv4 address, found without sending a single packet."""

from __future__ import annotations

import ipaddress
import socket


def _candidates() -> list[str]:
    out: list[str] = []
    try:
        for info in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET):
            out.append(info[4][0])
    except OSError:
        pass
    try:  # Linux: ask each interface for its address (ioctl SIOCGIFADDR; no traffic)
        import fcntl
        import struct
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _, name in socket.if_nameindex():
                try:
                    req = struct.pack("256s", name.encode()[:15])
                    addr = fcntl.ioctl(s.fileno(), 0x8915, req)[20:24]
                    out.append(socket.inet_ntoa(addr))
                except OSError:
                    continue
    except (ImportError, OSError, AttributeError):
        pass
    return out


def lan_ipv4() -> str:
    """The best guess of the address a phone on the same network should use:
    a private (RFC 1918) address first, then any non-loopback one, else 127.0.0.1."""
    return lan_ipv4_all()[0]


def lan_ipv4_all() -> list[str]:
    """Every address a phone might use, best first (see :func:`lan_ipv4`): a PC with a
    wired and a wireless network, or a VPN, has several."""
    addrs = []
    for a in _candidates():
        try:
            ip = ipaddress.IPv4Address(a)
        except ValueError:
            continue
        if not ip.is_loopback and not ip.is_link_local and a not in addrs:
            addrs.append(a)
    private = [a for a in addrs if ipaddress.IPv4Address(a).is_private]
    # 192.168.x and 10.x are the usual Wi-Fi and hotspot networks; 172.16-31.x is more
    # often a container or VM bridge: those last among the private ones
    private.sort(key=lambda a: a.startswith("172."))
    rest = [a for a in addrs if a not in private]
    return private + rest or ["127.0.0.1"]
