"""Turn a phones-tyrex trial (``shared/data/phones-tyrex/*.npz``) into the message bodies
Sensor Logger pushes (``shared/protocols/sensor-logger.md``), for the decoder's tests.

The npz holds, on a 100 Hz grid, the specific force ``acc`` (Android sign), ``gyr``,
``mag``, the OS's ``os_quat`` and the truth ``gt_quat`` (sensor -> ENU, y magnetic
north). What the app would push is made from them:

- gravity = the truth's "up" in sensor axes × 9.80665 (from ``gt_quat``; where the
  truth has a hole, from ``os_quat``); linear acceleration = acc − gravity;
- Android: ``totalacceleration`` = acc, ``accelerometer`` = linear, ``gravity``,
  ``gyroscope``, ``magnetometer``, ``orientation``; every sensor on its own clock (its
  own offset within a sample period plus a little jitter), ``accuracy`` on each reading;
- iOS: one timestamp per CoreMotion sample shared by all sensors, no
  ``totalacceleration``, ``accuracy`` on the magnetometer only; with Standardise off
  (the default) accelerometer, gravity (and the raw accelerometer, in g) negated.

**Orientation convention assumed** (the app does not document it): Android pushes the
rotation-vector quaternion as the OS gives it, sensor -> ENU (``ori="enu"``); iOS pushes
CMAttitude's quaternion in its ``XTrueNorthZVertical`` reference, i.e. sensor -> NWU
(x north, y west, z up; ``ori="nwu"``). ``ori`` also takes ``"enu-conj"`` /
``"nwu-conj"`` (world -> sensor) and ``"wrong"`` (ENU turned 45° about the vertical,
a convention no candidate of the checker explains). The quaternion fed is ``os_quat``
(the phone's own estimate, what the app would really see).

Times: epoch ns ints (~19 digits) that went through a double, as in real payloads.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

G_STD = 9.80665
EPOCH_NS = 1_760_000_000_000_000_000
DEVICE_ANDROID = "a8d4e0c2-61f3-4b9a-b7d5-0c9e2f4a6b13"
DEVICE_IOS = "8b5937fb-0000-4825-ba40-4bc646f93839"


def _qmul(a, b):
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def _rz(deg):
    h = math.radians(deg) / 2
    return np.array([math.cos(h), 0.0, 0.0, math.sin(h)])


def up_in_sensor(q):
    """World up (ENU z) in sensor axes for sensor->ENU quaternions (N, 4)."""
    w, x, y, z = np.asarray(q, float).T
    return np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1)


def app_quaternion(q_enu, ori: str):
    """Sensor->ENU quaternions -> what the app pushes under convention ``ori``."""
    q = np.asarray(q_enu, float)
    if ori == "enu":
        out = q
    elif ori == "enu-conj":
        out = q * [1, -1, -1, -1]
    elif ori == "nwu":           # ENU -> NWU is a turn of -90° about z
        out = _qmul(_rz(-90.0), q)
    elif ori == "nwu-conj":
        out = _qmul(_rz(-90.0), q) * [1, -1, -1, -1]
    elif ori == "wrong":
        out = _qmul(_rz(45.0), q)
    else:
        raise ValueError(ori)
    return out


def load(npz_path):
    d = np.load(Path(npz_path))
    return {k: d[k] for k in d.files}


def gravity_of(d):
    """The gravity reading the OS would give: truth's up × g (os_quat where no truth)."""
    gt, os_q = d["gt_quat"], d["os_quat"]
    up = up_in_sensor(np.where(np.isfinite(gt).all(axis=1)[:, None], gt, os_q))
    return up * G_STD


def _times_ns(t, offset_s, jitter_s, rng):
    """Epoch ns ints through a double (real stamps end in ...200, ...500)."""
    jit = rng.uniform(-jitter_s, jitter_s, len(t)) if jitter_s else 0.0
    ns = EPOCH_NS + np.round((t + offset_s + jit) * 1e9).astype(np.int64)
    return [int(float(v)) for v in ns.tolist()]


def _reading(name, t, keys, row, accuracy=None):
    r = {"name": name, "time": t,
         "values": {k: float(v) for k, v in zip(keys, row)}}
    if accuracy is not None:
        r["accuracy"] = accuracy
    return r


_XYZ = ("x", "y", "z")
_Q = ("qw", "qx", "qy", "qz")


def _bodies(streams, t_first, batch_s, session, device, rng, start_id, user_id=None):
    """streams: list of (name, times_ns list, keys, rows, accuracy) -> JSON bodies, one
    per batch window, readings of all sensors interleaved (shuffled) within a message."""
    per_msg: dict[int, list] = {}
    for name, times, keys, rows, acc in streams:
        for tns, row in zip(times, rows):
            if not np.isfinite(row).all():
                continue               # the app sends no NaN
            k = int(((tns - EPOCH_NS) / 1e9 - t_first) // batch_s)
            per_msg.setdefault(k, []).append(_reading(name, tns, keys, row, acc))
    bodies = []
    for i, k in enumerate(sorted(per_msg)):
        payload = per_msg[k]
        order = rng.permutation(len(payload))
        msg = {"messageId": start_id + i, "sessionId": session, "deviceId": device,
               "payload": [payload[j] for j in order]}
        if user_id is not None:
            msg["userId"] = user_id
        bodies.append(json.dumps(msg, separators=(",", ":")).encode())
    return bodies


# Android: each sensor's own clock offset (fraction of the 10 ms period) and jitter
ANDROID_OFFSETS = {"totalacceleration": 0.11, "accelerometer": 0.27, "gravity": 0.33,
                   "gyroscope": 0.05, "magnetometer": 0.61, "orientation": 0.29}
JITTER = 0.03


def row_index(time_ms, t, fs, offset_frac=0.0):
    """The npz rows that samples at ``time_ms`` (array) were made from."""
    s = (np.asarray(time_ms, float) - EPOCH_NS / 1e6) / 1e3 - offset_frac / fs
    return np.rint((s - t[0]) * fs).astype(int)


def messages_android(npz_path, batch_s=1.0, *, total=True, ori="enu", seconds=None,
                     session="3f1c2a9e-5b7d-4c11-9a0e-2d6f8b1c4e77",
                     device=DEVICE_ANDROID, seed=1, start_id=1):
    """An Android phone's pushes of the trial (first ``seconds`` only if given).
    ``total=False``: no totalacceleration (the decoder must pair accelerometer+gravity)."""
    d = load(npz_path)
    n = len(d["t"]) if seconds is None else int(seconds * d["fs"])
    t = d["t"][:n]
    rng = np.random.default_rng(seed)
    dt = 1.0 / float(d["fs"])
    g = gravity_of(d)[:n]
    acc = d["acc"][:n]
    # own offset per sensor within a period, jitter 0.3 ms: each sensor keeps its order
    # and the accelerometer's nearest gravity reading is the one of the same grid row
    spec = [("totalacceleration", _XYZ, acc),
            ("accelerometer", _XYZ, acc - g),
            ("gravity", _XYZ, g),
            ("gyroscope", _XYZ, d["gyr"][:n]),
            ("magnetometer", _XYZ, d["mag"][:n]),
            ("orientation", _Q, app_quaternion(d["os_quat"][:n], ori))]
    if not total:
        spec = spec[1:]
    streams = [(name, _times_ns(t, ANDROID_OFFSETS[name] * dt, JITTER * dt, rng), keys, rows, 3)
               for name, keys, rows in spec]
    return _bodies(streams, float(t[0]), batch_s, session, device, rng, start_id)


def messages_ios(npz_path, batch_s=1.0, standardise=False, *, ori="nwu", uncalibrated=False,
                 seconds=None, session="0ba5f3e8-0000-4c40-b9ea-95d7ed4d1132",
                 device=DEVICE_IOS, seed=2, start_id=1, user_id=None):
    """An iPhone's pushes: shared timestamps, iOS signs unless ``standardise``,
    ``uncalibrated`` adds accelerometeruncalibrated (g if not standardised)."""
    d = load(npz_path)
    n = len(d["t"]) if seconds is None else int(seconds * d["fs"])
    t = d["t"][:n]
    rng = np.random.default_rng(seed)
    times = _times_ns(t, 0.0, 0.1 / float(d["fs"]), rng)
    g = gravity_of(d)[:n]
    acc = d["acc"][:n]
    s = 1.0 if standardise else -1.0
    streams = [("gravity", times, _XYZ, s * g, None),
               ("accelerometer", times, _XYZ, s * (acc - g), None),
               ("gyroscope", times, _XYZ, d["gyr"][:n], None),
               ("magnetometer", times, _XYZ, d["mag"][:n], 2),
               ("orientation", times, _Q, app_quaternion(d["os_quat"][:n], ori), None)]
    if uncalibrated:
        streams.append(("accelerometeruncalibrated", times, _XYZ,
                        acc if standardise else -acc / G_STD, None))
    return _bodies(streams, float(t[0]), batch_s, session, device, rng, start_id, user_id)


# ---------------------------------------------------------------- delivery

def swapped(bodies, i):
    """Message i+1 delivered before message i."""
    out = list(bodies)
    out[i], out[i + 1] = out[i + 1], out[i]
    return out


def duplicated(bodies, i):
    """Message i delivered twice (right after itself)."""
    return list(bodies[:i + 1]) + [bodies[i]] + list(bodies[i + 1:])


def missing(bodies, i):
    """Message i never delivered."""
    return list(bodies[:i]) + list(bodies[i + 1:])


def deliver(stream, bodies, t0=0.0, period=1.0):
    """Decode the bodies one ``period`` apart on the wall clock; flush at the end. The
    released samples, in release order."""
    out = []
    now = t0
    for b in bodies:
        out.extend(stream.decode(b, now).samples)
        now += period
    out.extend(stream.due(now + 10.0))
    out.extend(stream.flush())
    return out
