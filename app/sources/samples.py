"""The one input boundary: the typed sample every source yields.

Every way data comes in (the Sensor Fusion app's TCP lines, Sensor Logger's and phyphox's
HTTP pushes, phyphox's remote access, the simulator, a replayed log) turns its wire format
into :class:`Sample` objects: the sensor (``tag``), the phone's own sample time and the
values in orientlab's frames and SI units (specific force in m/s², rad/s, µT; ORI the
phone's own orientation, scalar-first, sensor to world ENU). The ordering, the live core,
the recorder and the lab toolkit see samples, never a wire format.

What is physically impossible is defined here once (:data:`VALUE_LIMITS`), for every
source and every file reader.
"""

from __future__ import annotations

from dataclasses import dataclass

from app.params import GRAVITY

# tags whose values are vectors the estimators use
MOTION_TAGS = ("ACC", "GYR", "MAG", "ORI")


class DecodeError(ValueError):
    """Input from a phone app that cannot be used (a line, a message, a push's body): every
    source's own error derives from it. ``reason`` is a short key for counting; the message
    a short description (never the input itself)."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason

# Physically impossible readings, one definition for the live stream and every file
# reader (app.sources.readers): a vector whose norm is above its limit is no reading of a phone
# (a phone gyro saturates near 35 rad/s, an accelerometer near 16 g, a magnetometer near
# 5 mT only next to a magnet touching it; the Earth's field is 25-65 µT). Such a line is
# refused and counted (reason "impossible"), like a line that does not parse.
VALUE_LIMITS: dict[str, float] = {
    "GYR": 100.0,          # rad/s
    "ACC": 20.0 * GRAVITY,      # m/s² (20 g)
    "MAG": 2000.0,         # µT (2 mT)
}
VALUE_LIMITS["RAWGYR"] = VALUE_LIMITS["GYR"]
VALUE_LIMITS["RAWMAG"] = VALUE_LIMITS["MAG"]
# A time stamp beyond this many ms (about 3,000 years) is no clock reading.
MAX_TIME_MS = 1e14


def impossible(tag: str, values) -> bool:
    """True if the first three values of ``tag`` (a 3-vector sensor) have a norm above
    :data:`VALUE_LIMITS` (NaN is *not* impossible: it is a missing value)."""
    lim = VALUE_LIMITS.get(tag)
    if lim is None:
        return False
    x, y, z = values[0], values[1], values[2]
    if abs(x) > lim or abs(y) > lim or abs(z) > lim:   # also +-inf; no overflow below
        return True
    return x * x + y * y + z * z > lim * lim


# A quaternion whose squared norm is outside this is no attitude reading (a phone's is unit to
# its rounding); the three-value form (x, y, z of a rotation vector) completed with
# w = √(1 - x² - y² - z²), 0 when that is negative, is judged the same way.
QUAT_NORM2 = (0.5, 1.5)


def quaternion_reading(values) -> tuple[float, float, float, float] | None:
    """A phone's attitude reading (w, x, y, z, or x, y, z with w completed) as four floats
    with w >= 0 (the convention: q and -q are one attitude), or None when it is no unit
    quaternion (:data:`QUAT_NORM2`); NaN passes (missing)."""
    if len(values) == 3:
        x, y, z = values
        w2 = 1.0 - x * x - y * y - z * z
        q = (w2 ** 0.5 if w2 > 0.0 else 0.0, x, y, z)
    else:
        q = tuple(values[:4])
    n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
    if n2 != n2:        # NaN: a missing value, not an impossible one (as for the sensors)
        return q
    if not (QUAT_NORM2[0] < n2 < QUAT_NORM2[1]):    # also inf
        return None
    return (-q[0], -q[1], -q[2], -q[3]) if q[0] < 0.0 else q


def quaternion_rows(q):
    """Vectorised :func:`quaternion_reading` for (N, 4) readings: the rows with w >= 0, and
    which are no unit quaternion (bool (N,); NaN rows False, as missing)."""
    import numpy as np
    q = np.asarray(q, dtype=float)
    with np.errstate(invalid="ignore", over="ignore"):
        n2 = np.einsum("ij,ij->i", q, q)
        bad = ~((n2 > QUAT_NORM2[0]) & (n2 < QUAT_NORM2[1])) & ~np.isnan(n2)
    return np.where(q[:, :1] < 0.0, -q, q), bad


def impossible_rows(tag: str, v):
    """Vectorised :func:`impossible` for an (N, 3) array (bool (N,)); NaN rows False."""
    import numpy as np
    lim = VALUE_LIMITS[tag]
    v = np.asarray(v, dtype=float)
    with np.errstate(invalid="ignore", over="ignore"):
        big = (np.abs(v) > lim).any(axis=1)
        return big | (np.einsum("ij,ij->i", np.where(big[:, None], 0.0, v),
                                np.where(big[:, None], 0.0, v)) > lim * lim)


@dataclass(frozen=True, slots=True)
class Sample:
    """One reading: ``tag`` (ACC, GYR, MAG, ORI, ... as in the Sensor Fusion app's
    format), ``time_ms`` the phone's own sample time in milliseconds (int, or float for a
    source with sub-millisecond stamps), ``values`` in SI units and orientlab's frames
    (floats; str fields for text tags)."""
    time_ms: int | float    # the phone's own clock (per tag), never the arrival time
    tag: str
    values: tuple           # floats for numeric tags, str for text tags

    @property
    def t(self) -> float:
        return self.time_ms / 1000.0
