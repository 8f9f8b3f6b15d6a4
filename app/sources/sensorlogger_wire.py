"""Sensor Logger's push message off the wire: bytes in, readings as arrays out. No state
and no I/O: a message may be read on any thread (the server reads a long batch on a worker
thread); :class:`~app.sources.sensorlogger.SensorLoggerStream` applies what was read to a
phone's stream (its order, session, sign convention) on the event loop.

The format: ``shared/protocols/sensor-logger.md``. ``payload`` is a list of ``{name, time,
values, accuracy?}``. Names are compared lower-cased. Unknown names (and ``test``) are
counted in ``ignored`` and skipped; a reading without time or values, with a missing axis,
non-numeric, non-finite (NaN, inf) or physically impossible values
(:func:`~app.sources.samples.impossible`) is counted in ``invalid`` by reason and skipped;
everything else of the message is kept.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from app.sources.samples import MAX_TIME_MS, DecodeError, impossible_rows

__all__ = ["SensorLoggerError", "WireMessage", "read_message", "count_ignored"]

_MAX_NS = 9_000_000_000_000_000_000     # below int64's limit; MAX_TIME_MS is larger
_MAX_NS = min(_MAX_NS, int(MAX_TIME_MS * 1e6))

_XYZ = ("x", "y", "z")
_KEYS = {
    "totalacceleration": _XYZ, "accelerometer": _XYZ, "gravity": _XYZ,
    "accelerometeruncalibrated": _XYZ, "gyroscope": _XYZ, "gyroscopeuncalibrated": _XYZ,
    "magnetometer": _XYZ, "magnetometeruncalibrated": _XYZ,
    "orientation": ("qw", "qx", "qy", "qz"),
}
# the limit (samples.VALUE_LIMITS) each reading is checked against
_LIMIT_TAG = {
    "totalacceleration": "ACC", "accelerometer": "ACC", "gravity": "ACC",
    "accelerometeruncalibrated": "ACC", "gyroscope": "GYR", "gyroscopeuncalibrated": "GYR",
    "magnetometer": "MAG", "magnetometeruncalibrated": "MAG",
}
MAX_IGNORED_NAMES = 50     # distinct unknown names kept in the counter
_NUM = frozenset((int, float))    # JSON numbers (bool is not one)


# the largest messageId taken as one (a phone sending 1000 a second for 285 000 years): a
# larger one (10**400 from a script) made the session's gap count a 400-digit number and
# every later message a duplicate
MAX_MESSAGE_ID = 2 ** 53


class SensorLoggerError(DecodeError):
    """A message that cannot be used at all; ``reason`` is a short key for counting."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(reason, detail if len(detail) <= 80 else detail[:77] + "...")
        self.detail = detail


@dataclass
class WireMessage:
    """One message as :func:`read_message` read it, before a stream applies it."""
    key: tuple[str, str]                 # (deviceId, sessionId)
    mid: int | None                      # messageId (None: none, or not an integer)
    bad_mid: bool                        # a messageId that is no integer
    groups: dict = field(default_factory=dict)     # name -> (times ns, values)
    latest: int | None = None            # the newest reading's time (ns)
    accuracy: Counter = field(default_factory=Counter)   # readings with "accuracy", by name
    ignored: Counter = field(default_factory=Counter)
    invalid: Counter = field(default_factory=Counter)


def count_ignored(ignored: Counter, name: str, n: int = 1) -> None:
    """Count ``n`` readings of an unknown ``name``: at most :data:`MAX_IGNORED_NAMES`
    distinct names (40 characters each), the rest as ``(other)``: a stream of made-up
    names cannot grow the counter."""
    name = name[:40]
    if name in ignored or len(ignored) < MAX_IGNORED_NAMES:
        ignored[name] += n
    else:
        ignored["(other)"] += n


def _parse(payload: list, out: WireMessage) -> None:
    """The readings of a payload into ``out``: per name, times (ns) and values as arrays;
    what was wrong counted in ``out``'s counters."""
    rows: dict[str, tuple[list, list]] = {}
    accuracy, ignored, invalid = out.accuracy, out.ignored, out.invalid
    for r in payload:
        if type(r) is not dict:
            invalid["bad_reading"] += 1
            continue
        name = r.get("name")
        if type(name) is not str:
            invalid["no_name"] += 1
            continue
        keys = _KEYS.get(name)
        if keys is None:
            name = name.strip().lower()
            keys = _KEYS.get(name)
            if keys is None:
                count_ignored(ignored, name)
                continue
        t = r.get("time")
        if type(t) is not int:
            if t is None:
                invalid["no_time"] += 1
                continue
            if type(t) is float and math.isfinite(t):
                t = int(t)
            else:
                invalid["bad_time"] += 1
                continue
        if t <= 0 or t > _MAX_NS:
            invalid["bad_time"] += 1
            continue
        v = r.get("values")
        if type(v) is not dict:
            invalid["no_values"] += 1
            continue
        try:
            if len(keys) == 3:
                row = (v[keys[0]], v[keys[1]], v[keys[2]])
            else:
                row = (v[keys[0]], v[keys[1]], v[keys[2]], v[keys[3]])
        except KeyError:
            invalid["missing_axis"] += 1
            continue
        if not (type(row[0]) in _NUM and type(row[1]) in _NUM and type(row[2]) in _NUM
                and (len(row) == 3 or type(row[3]) in _NUM)):
            invalid["not_numeric"] += 1
            continue
        g = rows.get(name)
        if g is None:
            g = rows[name] = ([], [])
        g[0].append(t)
        g[1].append(row)
        if "accuracy" in r:
            accuracy[name] += 1
    groups = {}
    latest = None
    for name, (ts, vs) in rows.items():
        try:
            V = np.array(vs, dtype=float)
        except OverflowError:      # a JSON integer beyond any float
            fits = [not any(type(a) is int and abs(a) > 1e300 for a in row) for row in vs]
            invalid["impossible"] += fits.count(False)
            ts = [t for t, f in zip(ts, fits) if f]
            vs = [row for row, f in zip(vs, fits) if f]
            if not vs:
                continue
            V = np.array(vs, dtype=float)
        T = np.array(ts, dtype=np.int64)
        bad = ~np.isfinite(V).all(axis=1)
        if bad.any():
            invalid["not_finite"] += int(bad.sum())
        lim = _LIMIT_TAG.get(name)
        if lim is not None:
            imp = ~bad & impossible_rows(lim, np.where(bad[:, None], 0.0, V))
        else:   # a quaternion: norm near 1
            with np.errstate(invalid="ignore"):
                nq = np.linalg.norm(np.where(bad[:, None], 1.0, V), axis=1)
            imp = ~bad & ((nq < 0.9) | (nq > 1.1))
            V = V / np.where(bad | imp, 1.0, nq)[:, None]
        if imp.any():
            invalid["impossible"] += int(imp.sum())
        keep = ~(bad | imp)
        if not keep.all():
            T, V = T[keep], V[keep]
        if len(T):
            groups[name] = (T, V)
            mx = int(T.max())
            latest = mx if latest is None else max(latest, mx)
    out.groups, out.latest = groups, latest


def read_message(body: bytes) -> WireMessage:
    """One pushed message off the wire: its JSON and readings as arrays, with what was
    wrong in them counted. Raises :class:`SensorLoggerError`."""
    try:
        msg = json.loads(body)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise SensorLoggerError("bad_json", f"not JSON ({type(e).__name__}: {e})") from None
    if not isinstance(msg, dict):
        raise SensorLoggerError("bad_shape", f"not a JSON object (a {type(msg).__name__})")
    payload = msg.get("payload")
    if not isinstance(payload, list):
        what = "no payload" if payload is None else f"payload is a {type(payload).__name__}, not a list"
        raise SensorLoggerError("bad_shape", what)
    mid, bad_mid = msg.get("messageId"), False
    if type(mid) is not int:
        if isinstance(mid, float) and mid.is_integer():
            mid = int(mid)
        else:
            bad_mid = mid is not None
            mid = None
    if mid is not None and not 0 <= mid <= MAX_MESSAGE_ID:
        mid, bad_mid = None, True       # no app counts that far: its order cannot be trusted
    r = WireMessage((str(msg.get("deviceId")), str(msg.get("sessionId"))), mid, bad_mid)
    _parse(payload, r)
    return r
