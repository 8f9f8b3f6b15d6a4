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
    addrs = []
    for a in _candidates():
        try:
            ip = ipaddress.IPv4Address(a)
        except ValueError:
            continue
        if not ip.is_loopback and not ip.is_link_local and a not in addrs:
            addrs.append(a)
    private = [a for a in addrs if ipaddress.IPv4Address(a).is_private]
    return (private or addrs or ["127.0.0.1"])[0]
