"""Sensor Logger's HTTP push (and MQTT) messages: bytes in, samples out. No I/O.

The format and what is (not) known about it: ``shared/protocols/sensor-logger.md``.
One :class:`SensorLoggerStream` holds the state of one phone's push stream::

    stream = SensorLoggerStream()
    batch = stream.decode(body, now=time.monotonic())   # raises SensorLoggerError
    # or in two steps, the first on any thread (it touches no state of the stream):
    #   read = SensorLoggerStream.read(body); batch = stream.take(read, now)
    if batch.new_session: ...                           # start a fresh stream
    samples = batch.samples                             # -> SampleOrderer
    samples += stream.due(time.monotonic())             # now and then
    samples += stream.flush()                           # end of stream

What it does
------------
*Readings* are read off the wire by :mod:`app.sources.sensorlogger_wire` (what is
counted in ``ignored`` and ``invalid``, and why); this module applies them to a stream.

*Sources.* One source per tag and session, the best one seen: ACC from
``totalacceleration`` (Android's specific force, as is), else ``accelerometer`` +
``gravity`` (linear acceleration + the OS's gravity, each accelerometer reading paired
with the gravity reading nearest in time; identical times on iOS), else
``accelerometeruncalibrated``, else ``gravity`` alone (the tilt without the shakes); GYR from ``gyroscope`` else ``gyroscopeuncalibrated``;
MAG from ``magnetometer`` else ``magnetometeruncalibrated`` (hard-iron offsets beyond
the limit are skipped as impossible); ORI from ``orientation`` once its convention is
checked (:class:`OrientationCheck`).

*Signs.* iOS with "Standardise Units & Frames" off (the app's default) reports
acceleration and gravity negated against Android, and the raw accelerometer in g. The
convention is detected per session from the data (see :meth:`SensorLoggerStream.status`
``reasons``; the field's dip from the calibrated ``magnetometer`` only, northern
hemisphere assumed), or set by the presenter (:meth:`SensorLoggerStream.set_convention`);
``hints`` say what to change for a right pose.
Until the evidence decides it, a session's first samples are held, for at most
``START_HOLD_S`` of the phone's time (then the app's default goes): released with a
guessed sign, they would align the filters upside down.

*Messages.* ``messageId`` grows by one per message of a session. A message is released
at once when it is the next one (or the first); one that arrives ahead of a missing one
is held until the missing one comes or ``hold_s`` has passed (then the gap is counted);
a late one (its place given up) is released at once, less its readings more than 2 s
behind the newest released (``_STALE_NS``: dropped, counted ``late_readings``); a
duplicate is dropped whole.
What is released together is sorted per sensor (exact duplicate times dropped, also a
time released lately: a reading sent again in a later message) and
merged by time; the downstream SampleOrderer does the fine cross-sensor ordering.

Times: ``Sample.time_ms`` = the reading's epoch ``time`` (ns) / 1e6, as float, computed
from the integer so that sub-millisecond precision survives.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from app.params import GRAVITY
from app.quaternion import Q_many, quat_conj_many, quat_from_rotvec_many, quat_mul_many
from app.sources.ordering import STOPPED_S
from app.sources.samples import Sample, impossible_rows
from app.sources.sensorlogger_wire import (SensorLoggerError, WireMessage, count_ignored,
                                           read_message)

__all__ = ["SensorLoggerError", "Batch", "SensorLoggerStream", "OrientationCheck",
           "CONVENTIONS", "G_STD"]

G_STD = 9.80665           # the app's g (iOS raw accelerometer unit)
# A session's first samples wait at most this long (s, the phone's time) for the evidence of
# the accelerometer's sign: a filter aligned on the wrong sign starts upside down
START_HOLD_S = 2.0
CONVENTIONS = ("auto", "android", "ios", "ios-standardised")
# per tag, the sources in order of preference
_SOURCES = {
    # the phone's gravity alone last: the tilt without the shakes, better than no tilt
    "ACC": ("totalacceleration", "accelerometer+gravity", "accelerometeruncalibrated", "gravity"),
    "GYR": ("gyroscope", "gyroscopeuncalibrated"),
    "MAG": ("magnetometer", "magnetometeruncalibrated"),
    "ORI": ("orientation",),
}
# A late message's readings this far behind the newest released are dropped and counted
# late: the downstream orderer would take a run of them for the phone's clock stepping back
# (its jump_s, 2 s) and move the stream's clock on by seconds for good
_STALE_NS = 2_000_000_000
# after this many messages of other sensors without one orientation reading, the page says
# the app sends none (a message is about a second: long past the start's hold)
NO_ORI_AFTER = 5
_PAIR_MAX_NS = 100_000_000  # accelerometer/gravity pairing: at most 0.1 s apart
_RATE_HISTORY = 256
# the readings' times kept per sensor to drop one sent again in a later message (a push
# repeated with a new messageId): about 2.5 s at 400 Hz, more than a batch period
SENT_KEPT = 1024


@dataclass
class Batch:
    """What one :meth:`SensorLoggerStream.decode` released. ``new_session``: this message
    starts a new (deviceId, sessionId) recording (start a fresh stream). ``ended``: the
    samples the previous session still held, released at its end (they belong to the
    old stream; empty almost always)."""
    samples: list[Sample]
    new_session: bool
    ended: list[Sample] = field(default_factory=list)
    late: int = 0          # readings of a late message dropped as too late (``_STALE_NS``)


def _by_time(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Parts ``(times, values)`` of one sensor as one, sorted by time (stable: equal times
    keep their order)."""
    if len(parts) == 1:
        T, V = parts[0]
    else:
        T = np.concatenate([p[0] for p in parts])
        V = np.concatenate([p[1] for p in parts])
    o = np.argsort(T, kind="stable")
    return T[o], V[o]


def _nearest(tq: np.ndarray, tr: np.ndarray, max_dt) -> tuple[np.ndarray, np.ndarray]:
    """For each time in ``tq``, the index of the nearest time in the sorted ``tr`` and
    whether it lies within ``max_dt``."""
    if len(tr) == 0:
        return np.zeros(len(tq), dtype=np.intp), np.zeros(len(tq), dtype=bool)
    j = np.searchsorted(tr, tq)
    j = np.clip(j, 1, len(tr) - 1) if len(tr) > 1 else np.zeros(len(tq), dtype=np.intp)
    if len(tr) > 1:
        left = tr[j - 1]
        pick_left = np.abs(tq - left) <= np.abs(tr[j] - tq)
        j = np.where(pick_left, j - 1, j)
    return j, np.abs(tr[j] - tq) <= max_dt


# ---------------------------------------------------------------- orientation check

class OrientationCheck:
    """Which convention the app's ``orientation`` quaternion uses, checked against physics.

    Candidates: the quaternion as sent or conjugated, each followed by a fixed turn of
    the world frame about the vertical by 0/90/180/270° (90° maps an x-north, z-up (NWU)
    reference such as iOS's ``XTrueNorthZVertical`` to ENU). Over samples near rest
    (gyro < 0.15 rad/s, |specific force| within 0.4 m/s² of g), a candidate fits a
    sample when its world "up" matches the measured specific force within ``tilt_deg``
    and its "north" the horizontal field within ``heading_deg``. Once ``need_s`` of rest
    data are seen and one candidate fits at least half of them and clearly more than
    any other (twice as long, or ``need_s / 2`` longer), it is taken (for the session).
    A phone lying still with its top near a multiple of 45° from north fits two
    candidates alike (conjugated, a flat phone's heading changes sign, and one of the
    world's turns by 90° makes up for it there): that rest tells them apart no more than
    it tells them from the rest, and half a ``need_s`` at a heading between those then
    decides (a fraction of all the rest seen never did: 38 s at north held it back
    for good). Cost: a few vectorised numpy operations per released batch.
    """

    TURNS = (0, 90, 180, 270)

    def __init__(self, tilt_deg: float = 3.0, heading_deg: float = 15.0,
                 need_s: float = 2.0, give_up_s: float = 4.0):
        self.tilt_deg = tilt_deg
        self.heading_deg = heading_deg
        self.need_s = need_s
        self.give_up_s = give_up_s
        self.names = [f"{'conjugated' if c else 'as sent'}, world turned {k}°"
                      for c in (False, True) for k in self.TURNS]
        self.reset()

    def reset(self) -> None:
        self.rest_s = 0.0
        self.fit_s = np.zeros(len(self.names))
        self.chosen: int | None = None

    @property
    def state(self) -> str:
        if self.chosen is not None:
            return "ok"
        if self.rest_s == 0.0:
            return "unchecked"
        if self.rest_s >= self.give_up_s and self._best()[1] < 0.5:
            return "left out"
        return "checking"

    def _best(self) -> tuple[int, float, float]:
        if self.rest_s <= 0.0:
            return 0, 0.0, 0.0
        frac = self.fit_s / self.rest_s
        order = np.argsort(-frac, kind="stable")
        return int(order[0]), float(frac[order[0]]), float(frac[order[1]])

    def message(self) -> str:
        """The state in words, for the page (what the app's orientation is, in its place)."""
        st = self.state
        if st == "ok":
            return f"checked ({self.names[self.chosen]})"
        if st == "left out":
            return "left out: its convention did not match gravity and the field"
        if st == "checking":
            if self.rest_s >= self.need_s:
                i, best, second = self._best()
                if best >= 0.5:
                    return ("not yet checked: the phone's rest fits two conventions alike (its "
                            "top points near a multiple of 45° from north); turn it flat by about "
                            "20-30° and hold it still a moment")
            return f"not yet checked ({self.rest_s:.1f} s of {self.need_s:g} s near rest seen)"
        return "not yet checked (hold the phone still for a moment)"

    def status(self) -> dict:
        i, best, _ = self._best()
        return {"state": self.state, "message": self.message(),
                "convention": None if self.chosen is None else self.names[self.chosen],
                "rest_s": round(self.rest_s, 2),
                "best": self.names[i] if self.rest_s > 0 else None,
                "best_fit": round(best, 3)}

    def to_enu(self, q: np.ndarray, cand: int | None = None) -> np.ndarray:
        """The app's quaternions (N, 4) in candidate ``cand``'s reading: sensor->ENU, w >= 0."""
        cand = self.chosen if cand is None else cand
        conj, k = divmod(cand, len(self.TURNS))
        base = quat_conj_many(q) if conj else q
        turn = quat_from_rotvec_many(np.array([0.0, 0.0, math.radians(self.TURNS[k])]))
        out = quat_mul_many(turn, base)
        out /= np.linalg.norm(out, axis=1, keepdims=True)
        return np.where(out[:, :1] < 0.0, -out, out)

    def feed(self, t_ori, q, t_acc, f, t_mag, m, t_gyr, w) -> None:
        """Evidence from one released batch (times in ns, sorted per sensor)."""
        if self.chosen is not None or len(t_ori) == 0 or len(t_acc) == 0 or len(t_mag) == 0:
            return
        ia, oka = _nearest(t_ori, t_acc, 25_000_000)
        im, okm = _nearest(t_ori, t_mag, 50_000_000)
        fa = f[ia]
        ok = oka & okm & (np.abs(np.linalg.norm(fa, axis=1) - GRAVITY) < 0.4)
        if len(t_gyr):
            ig, okg = _nearest(t_ori, t_gyr, 25_000_000)
            ok &= okg & (np.linalg.norm(w[ig], axis=1) < 0.15)
        n = int(ok.sum())
        if n == 0:
            return
        dt = float(np.median(np.diff(t_ori))) / 1e9 if len(t_ori) > 1 else 0.01
        dt = min(max(dt, 0.001), 0.1)
        qq, fa, mm = q[ok], fa[ok], m[im[ok]]
        fa = fa / np.linalg.norm(fa, axis=1, keepdims=True)
        cos_tilt = math.cos(math.radians(self.tilt_deg))
        fits = []
        for conj in (False, True):
            R = Q_many(quat_conj_many(qq) if conj else qq)
            up = R[:, 2, :]                                   # world up in sensor axes
            tilt_ok = np.einsum("ij,ij->i", up, fa) >= cos_tilt
            mw = np.einsum("nij,nj->ni", R, mm)               # field in the world
            horiz = np.hypot(mw[:, 0], mw[:, 1]) > 3.0        # µT
            head = np.degrees(np.arctan2(mw[:, 0], mw[:, 1]))  # from north, east positive
            for k in self.TURNS:
                # turning the world by k (counter-clockwise) moves the heading by -k
                err = (head - k + 180.0) % 360.0 - 180.0
                fits.append(int((tilt_ok & horiz & (np.abs(err) <= self.heading_deg)).sum()))
        self.rest_s += n * dt
        self.fit_s += np.array(fits, dtype=float) * dt
        if self.rest_s >= self.need_s:
            i, best, second = self._best()
            apart_s = (best - second) * self.rest_s          # how much longer the best fits
            if best >= 0.5 and (second <= 0.5 * best or apart_s >= 0.5 * self.need_s):
                self.chosen = i


# ---------------------------------------------------------------- messages

@dataclass
class _Message:
    mid: int | None
    groups: dict            # name -> (times ns int64 (N,), values float (N, k))
    arrival: float


def _short(s: str | None) -> str | None:
    if s is None:
        return None
    s = str(s)
    return s if len(s) <= 8 else s[:8] + "…"


class SensorLoggerStream:
    """The state of one phone's push stream (see the module's doc).

    ``now`` (given to :meth:`decode` and :meth:`due`) is the receiver's wall clock in
    seconds (``time.time()``): held messages wait ``hold_s`` of it, and the status's
    ``clock_offset_s`` is the phone's epoch minus it (about minus the batch period
    when both clocks agree). A session's first samples wait at most ``start_hold_s`` of
    the phone's time for the evidence of the accelerometer's sign (0: they do not wait)."""

    def __init__(self, hold_s: float = 1.5, start_hold_s: float = START_HOLD_S):
        self.hold_s = float(hold_s)
        self.start_hold_s = float(start_hold_s)
        self._override: str | None = None
        self.rejected: Counter = Counter()     # whole messages refused, by reason
        self.sessions = 0
        self._key: tuple | None = None
        self._ended: set = set()
        self._reset_session()

    # ------------------------------------------------------------ session state
    def _reset_session(self) -> None:
        self.messages = 0
        self.gaps = 0
        self.out_of_order = 0
        self.duplicates = 0
        self.late = 0
        self.late_readings = 0                 # of late messages, dropped (_STALE_NS)
        self.ignored: Counter = Counter()
        self.invalid: Counter = Counter()
        self.unused: Counter = Counter()       # readings of a source not chosen
        self._next: int | None = None          # next messageId expected
        self._max_id: int | None = None
        self._seen: set[int] = set()
        self._held: dict[int, _Message] = {}
        self._sources: dict[str, str] = {}
        self.platform: str | None = None
        self.platform_reason: str | None = None
        self._conv: str = "ios"
        self._conv_source = "assumed"
        self._conv_strong = False               # decided by decisive evidence
        self._dip = [0, 0]                      # rest samples agreeing / disagreeing
        self._pending: list[dict] = []          # the first samples, while the sign is unknown
        self._released = False                  # samples of this session went out
        self.reasons: list[str] = []
        self._last_gravity: tuple | None = None
        self._recent: dict[str, deque] = {}
        self._sent_t: dict[str, np.ndarray] = {}   # per name, the times released lately
        self._last_ms: float | None = None
        self._ori_last_ms: float | None = None   # the newest orientation reading (released or not)
        self._offsets: deque = deque(maxlen=21)
        self.ori = OrientationCheck()

    @property
    def waiting(self) -> bool:
        """Samples of this session are held until the accelerometer's sign is known."""
        return bool(self._pending)

    def _reason(self, text: str) -> None:
        if text not in self.reasons:
            self.reasons.append(text)

    # ------------------------------------------------------------ convention
    @property
    def convention(self) -> str:
        """The acceleration convention in force: android, ios (negate) or ios-standardised."""
        return self._override or self._conv

    @property
    def convention_source(self) -> str:
        return "presenter" if self._override else self._conv_source

    def set_convention(self, value: str) -> None:
        """The presenter's override: ``auto``, ``android``, ``ios`` (Standardise off:
        negate) or ``ios-standardised``. Kept across sessions until set back to auto."""
        if value not in CONVENTIONS:
            raise ValueError(f"convention must be one of {', '.join(CONVENTIONS)}; "
                             f"got {str(value)[:40]!r}")
        new = None if value == "auto" else value
        if new != self._override:
            self._override = new
            self.ori.reset()

    def _set_conv(self, conv: str, reason: str, strong: bool) -> None:
        if self._conv_strong and not strong:
            return
        changed = conv != self._conv
        self._conv = conv
        self._conv_source = "detected"
        self._conv_strong = self._conv_strong or strong
        self._reason(reason)
        if changed and self._override is None:
            self.ori.reset()

    def _set_platform(self, platform: str, reason: str) -> None:
        if self.platform == platform:
            return
        self.platform = platform
        self.platform_reason = reason
        self._reason(reason)
        if platform == "android":
            self._conv_strong = False       # iOS evidence before was wrong
            self._set_conv("android", "Android: no sign change", strong=True)

    # ------------------------------------------------------------ decoding
    # one pushed message off the wire (touches no state of a stream: any thread may run it)
    read = staticmethod(read_message)

    def count_rejected(self, e: SensorLoggerError) -> None:
        """Count a message :meth:`read` refused."""
        self.rejected[e.reason] += 1

    def decode(self, body: bytes, now: float) -> Batch:
        """One pushed message -> the samples it (and what it unblocks) releases
        (:meth:`read`, then :meth:`take`)."""
        try:
            r = self.read(body)
        except SensorLoggerError as e:
            self.count_rejected(e)
            raise
        return self.take(r, now)

    def take(self, r: WireMessage, now: float) -> Batch:
        """A message :meth:`read` read, applied to the stream: the samples it (and what it
        unblocks) releases."""
        key = r.key
        new_session = False
        ended: list[Sample] = []
        if key != self._key:
            if key in self._ended:     # a straggler of a finished recording
                self.rejected["stale_session"] += 1
                return Batch([], False)
            if self._key is not None:
                ended = self.flush()
                self._ended.add(self._key)
            self._key = key
            self.sessions += 1
            self._reset_session()
            new_session = True
        mid = r.mid
        if r.bad_mid:
            self.invalid["bad_message_id"] += 1
        if mid is not None and mid in self._seen:
            self.duplicates += 1
            return Batch(self.due(now), new_session, ended)
        self.messages += 1
        dropped = 0
        self.invalid.update(r.invalid)
        for name, n in r.ignored.items():
            count_ignored(self.ignored, name, n)
        if r.latest is not None:
            self._offsets.append(r.latest / 1e9 - now)
        self._detect_platform(r.groups, r.accuracy)
        m = _Message(mid, r.groups, now)
        release: list[_Message] = []
        if mid is None:
            release.append(m)
        else:
            self._seen.add(mid)
            if self._max_id is not None and mid < self._max_id:
                self.out_of_order += 1
            self._max_id = mid if self._max_id is None else max(self._max_id, mid)
            if self._next is None or mid == self._next:
                release.append(m)
                self._next = mid + 1
                release.extend(self._run())
            elif mid < self._next:         # its place was given up: late
                self.late += 1
                self.gaps = max(0, self.gaps - 1)
                dropped = self._drop_stale(m)
                release.append(m)
            else:
                self._held[mid] = m
            if len(self._seen) > 4096:
                lo = self._next - 2048
                self._seen = {i for i in self._seen if i >= lo}
        release = self._timed_out(now) + release
        return Batch(self._emit(release), new_session, ended, dropped)

    def _drop_stale(self, m: _Message) -> int:
        """Drop a late message's readings more than ``_STALE_NS`` behind the newest
        released (counted in ``late_readings``); how many went."""
        if self._last_ms is None:
            return 0
        limit = int(self._last_ms * 1e6) - _STALE_NS
        n = 0
        for name, (T, V) in list(m.groups.items()):
            keep = T >= limit
            if not keep.all():
                n += int((~keep).sum())
                if keep.any():
                    m.groups[name] = (T[keep], V[keep])
                else:
                    del m.groups[name]
        self.late_readings += n
        return n

    def _run(self) -> list[_Message]:
        out = []
        while self._next in self._held:
            out.append(self._held.pop(self._next))
            self._next += 1
        return out

    def _timed_out(self, now: float) -> list[_Message]:
        out: list[_Message] = []
        while self._held and min(m.arrival for m in self._held.values()) + self.hold_s <= now:
            first = min(self._held)
            self.gaps += first - self._next
            self._next = first
            out.extend(self._run())
        return out

    def due(self, now: float) -> list[Sample]:
        """The samples of held messages whose missing predecessor did not come within
        ``hold_s`` (the gap is counted)."""
        return self._emit(self._timed_out(now))

    def flush(self) -> list[Sample]:
        """Release everything held (end of stream)."""
        out: list[_Message] = []
        while self._held:
            first = min(self._held)
            self.gaps += first - self._next
            self._next = first
            out.extend(self._run())
        return self._emit(out, force=True)

    # ------------------------------------------------------------ detection
    def _detect_platform(self, groups: dict, accuracy: Counter) -> None:
        """Android's signs (totalacceleration, accuracy on accelerometer/gyroscope) win
        over iOS's (readings of one CoreMotion sample sharing their time stamp)."""
        if self.platform == "android":
            return
        if "totalacceleration" in groups:
            self._set_platform("android", "totalacceleration present: Android")
            return
        if accuracy["accelerometer"] or accuracy["gyroscope"]:
            self._set_platform("android", "accuracy on accelerometer/gyroscope: Android")
            return
        if self.platform is not None:
            return
        # Android's fused sensors (gravity, linear acceleration) may share a stamp with
        # each other, not with the gyroscope
        tg = groups.get("gyroscope", groups.get("gyroscopeuncalibrated"))
        for other in ("accelerometer", "gravity"):
            ta = groups.get(other)
            if ta is not None and tg is not None:
                shared = np.isin(ta[0], tg[0]).mean()
                if shared >= 0.5:
                    self._set_platform("ios", f"{other} and gyroscope share timestamps: iOS")
                    return

    def _check_uncal(self, V: np.ndarray) -> None:
        if self._conv_strong or not len(V):
            return
        mag = float(np.median(np.linalg.norm(V, axis=1)))
        if 0.5 < mag < 1.6:
            if self.platform is None:
                self.platform, self.platform_reason = "ios", "raw accelerometer in g: iOS"
            self._set_conv("ios", "raw accelerometer in g: iOS, Standardise off", strong=True)
        elif 6.0 < mag < 14.0:
            conv = "android" if self.platform == "android" else "ios-standardised"
            self._set_conv(conv, "raw accelerometer in m/s²: no sign change", strong=True)

    def _check_dip(self, t_acc, f_android, t_mag, m, t_gyr, w) -> None:
        """Sign of the field's dip against the measured up (f in Android sign, i.e. as
        it would be *without* negation): negative in the northern hemisphere. ``f`` is the
        specific force, used where the phone is still (|f| = g, gyroscope below 0.15
        rad/s); or the app's gravity (``t_gyr`` None), used moving or not: a recording that
        starts in motion has no still sample within the session's first seconds."""
        if self._conv_strong or self.platform == "android" or not len(t_acc) or not len(t_mag):
            return
        if t_gyr is None:
            ok = np.linalg.norm(f_android, axis=1) > 0.5 * GRAVITY
        else:
            ok = np.abs(np.linalg.norm(f_android, axis=1) - GRAVITY) < 0.4
        im, okm = _nearest(t_acc, t_mag, 50_000_000)
        ok &= okm
        if t_gyr is not None and len(t_gyr):
            ig, okg = _nearest(t_acc, t_gyr, 25_000_000)
            ok &= okg & (np.linalg.norm(w[ig], axis=1) < 0.15)
        if not ok.any():
            return
        fa = f_android[ok]
        mm = m[im[ok]]
        s = np.einsum("ij,ij->i", fa, mm) / (np.linalg.norm(fa, axis=1) * np.linalg.norm(mm, axis=1))
        lim = math.sin(math.radians(20.0))
        self._dip[0] += int((s < -lim).sum())    # Android sign gives a northern dip
        self._dip[1] += int((s > lim).sum())
        n = self._dip[0] + self._dip[1]
        if n >= 50:
            if self._dip[0] >= 0.8 * n:
                self._set_conv("ios-standardised",
                               "field dips against gravity as sent: iOS, Standardise on "
                               "(northern hemisphere assumed)", strong=False)
            elif self._dip[1] >= 0.8 * n:
                self._set_conv("ios", "field dips along gravity as sent: iOS, Standardise off "
                               "(northern hemisphere assumed)", strong=False)

    # ------------------------------------------------------------ samples
    def _choose(self, tag: str, present) -> str | None:
        """The session's source for ``tag``: the best one seen so far."""
        cur = self._sources.get(tag)
        order = _SOURCES[tag]
        for src in order:
            if src == cur:
                return cur
            if src in present:
                self._sources[tag] = src
                return src
        return cur

    def _emit(self, msgs: list[_Message], force: bool = False) -> list[Sample]:
        if not msgs:
            return self._release({}, force)
        # all readings released together, per name, sorted by time, exact duplicates out
        by: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for name in {n for m in msgs for n in m.groups}:
            T, V = _by_time([m.groups[name] for m in msgs if name in m.groups])
            if len(T) > 1:
                keep = np.empty(len(T), dtype=bool)
                keep[0] = True
                np.not_equal(T[1:], T[:-1], out=keep[1:])
                if not keep.all():
                    self.invalid["duplicate_time"] += int((~keep).sum())
                    T, V = T[keep], V[keep]
            sent = self._sent_t.get(name)
            if sent is not None and len(T):
                again = np.isin(T, sent)      # a reading sent again in a later message
                if again.any():
                    self.invalid["duplicate_time"] += int(again.sum())
                    T, V = T[~again], V[~again]
            if len(T):
                prev = self._sent_t.get(name)
                self._sent_t[name] = (T[-SENT_KEPT:] if prev is None
                                      else np.concatenate((prev, T))[-SENT_KEPT:])
            by[name] = (T, V)
        present = set(by)
        if "accelerometer" in present and ("gravity" in present or self._last_gravity is not None):
            present.add("accelerometer+gravity")
        if "accelerometeruncalibrated" in by:
            self._check_uncal(by["accelerometeruncalibrated"][1])
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        used = set()
        for tag in ("GYR", "MAG"):
            src = self._choose(tag, present)
            if src in by:
                out[tag] = by[src]
                used.add(src)
        # specific force, in Android sign before the convention is applied
        src = self._choose("ACC", present)
        f_and = None
        if src == "totalacceleration" and src in by:
            t_f, f_and = by[src]
            used.add(src)
        elif src == "accelerometer+gravity" and "accelerometer" in by:
            t_a, a = by["accelerometer"]
            t_g, g = by.get("gravity", (np.zeros(0, np.int64), np.zeros((0, 3))))
            if self._last_gravity is not None:
                lt, lv = self._last_gravity
                sel = lt < (t_g[0] if len(t_g) else lt + 1)
                t_g = np.concatenate([lt[sel], t_g])
                g = np.concatenate([lv[sel], g])
            j, ok = _nearest(t_a, t_g, _PAIR_MAX_NS)
            if not ok.all():
                self.invalid["unpaired"] += int((~ok).sum())
            t_f, f_and = t_a[ok], a[ok] + g[j[ok]]
            used.update(("accelerometer", "gravity"))
        elif src == "accelerometeruncalibrated" and src in by:
            t_f, f_and = by[src]
            used.add(src)
        elif src == "gravity" and src in by:
            t_f, f_and = by[src]
            used.add(src)
        if "gravity" in by:
            t_g, g = by["gravity"]
            self._last_gravity = (t_g[-1:], g[-1:])
        for name in by:
            if name not in used and name != "orientation" and not (
                    name == "gravity" and src in ("accelerometer+gravity", "gravity")):
                self.unused[name] += len(by[name][0])
        if f_and is not None:
            gyr = out.get("GYR", (np.zeros(0, np.int64), np.zeros((0, 3))))
            mag = out.get("MAG", (np.zeros(0, np.int64), np.zeros((0, 3))))
            if src == "accelerometeruncalibrated":
                scale = G_STD if self._looks_in_g(f_and) else 1.0
                f_and = f_and * scale
            if self._sources.get("MAG") != "magnetometer":
                # the raw field's hard-iron offset (up to hundreds of µT) turns its dip any way
                mag = (np.zeros(0, np.int64), np.zeros((0, 3)))
            if self._override is None:
                if "gravity" in by:     # the app's gravity: no motion in it, moving or not
                    self._check_dip(by["gravity"][0], by["gravity"][1], mag[0], mag[1], None, None)
                else:
                    self._check_dip(t_f, f_and, mag[0], mag[1], gyr[0], gyr[1])
            out["ACC"] = (t_f, f_and)        # Android's sign: the convention is applied at release
        if "orientation" in by:
            out["ORI"] = by["orientation"]   # the app's own: checked at release
        return self._release(out, force)

    def _release(self, out: dict, force: bool) -> list[Sample]:
        """Apply the sign convention and release; or, while the sign is unknown, hold the
        session's first samples (a filter aligned on samples of the wrong sign starts upside
        down) until the evidence decides it, for at most ``start_hold_s`` of the phone's time
        (then the app's default goes), or until ``force`` (the end of the stream)."""
        if out:
            self._pending.append(out)
        if not self._pending:
            return []
        unknown = self._override is None and self._conv_source == "assumed"
        if unknown and not force and not self._released:
            times = [T for o in self._pending for T, _ in o.values() if len(T)]
            if times and max(int(T[-1]) for T in times) - min(int(T[0]) for T in times) \
                    < self.start_hold_s * 1e9:
                return []
        pending, self._pending = self._pending, []
        self._released = True                 # the session's samples flow: no more waiting
        out = {tag: _by_time([o[tag] for o in pending if tag in o])
               for tag in {tag for o in pending for tag in o}}
        if "ACC" in out:
            t_f, f_and = out["ACC"]
            f = -f_and if self.convention == "ios" else f_and
            bad = impossible_rows("ACC", f)
            if bad.any():
                self.invalid["impossible"] += int(bad.sum())
                t_f, f = t_f[~bad], f[~bad]
            out["ACC"] = (t_f, f)
        if "ORI" in out:
            t_o, q = out.pop("ORI")
            acc = out.get("ACC", (np.zeros(0, np.int64), np.zeros((0, 3))))
            gyr = out.get("GYR", (np.zeros(0, np.int64), np.zeros((0, 3))))
            mag = out.get("MAG", (np.zeros(0, np.int64), np.zeros((0, 3))))
            self._sources.setdefault("ORI", "orientation")
            if len(t_o):
                t_new = float(t_o.max()) / 1e6
                self._ori_last_ms = t_new if self._ori_last_ms is None else max(self._ori_last_ms, t_new)
            self.ori.feed(t_o, q, acc[0], acc[1], mag[0], mag[1], gyr[0], gyr[1])
            if self.ori.chosen is not None:
                out["ORI"] = (t_o, self.ori.to_enu(q))
            else:
                self.unused["orientation"] += len(t_o)
        return self._samples(out)

    def _looks_in_g(self, f: np.ndarray) -> bool:
        """The raw accelerometer's unit: g (iOS, Standardise off) or m/s²."""
        if self.convention == "ios":
            return True
        if self.convention_source == "presenter" or not len(f):
            return False
        return float(np.median(np.linalg.norm(f, axis=1))) < 4.0

    def _samples(self, out: dict) -> list[Sample]:
        tags, times, vals = [], [], []
        for tag, (T, V) in out.items():
            if not len(T):
                continue
            ms = (T // 1_000_000).astype(float) + (T % 1_000_000) / 1e6
            times.append(ms)
            tags.extend([tag] * len(T))
            vals.extend(map(tuple, V.tolist()))
            rec = self._recent.get(tag)
            if rec is None:
                rec = self._recent[tag] = deque(maxlen=_RATE_HISTORY)
            rec.extend(ms[-_RATE_HISTORY:].tolist())
            last = float(ms[-1])
            if self._last_ms is None or last > self._last_ms:
                self._last_ms = last
        if not times:
            return []
        allt = np.concatenate(times)
        order = np.argsort(allt, kind="stable")
        tl = allt.tolist()
        return [Sample(tl[i], tags[i], vals[i]) for i in order.tolist()]

    # ------------------------------------------------------------ status
    def rates(self) -> dict[str, float | None]:
        out = {}
        for tag, rec in self._recent.items():
            if len(rec) > 1:
                ts = sorted(rec)
                span = (ts[-1] - ts[0]) / 1000.0
                out[tag] = round((len(ts) - 1) / span, 2) if span > 0 else None
            else:
                out[tag] = None
        return out

    def _reasons_now(self) -> list[str]:
        out = list(self.reasons)
        if self._override is not None:
            out.append(f"set by the presenter: {self._override}")
        elif self._conv_source == "assumed" and self._pending and not self._released:
            out.append("no sign evidence yet: the first samples wait for it "
                       f"(at most {self.start_hold_s:g} s)")
        elif self._conv_source == "assumed":
            out.append("no sign evidence yet: iOS with Standardise off assumed (the app's default)")
        return out

    def hints(self) -> list[str]:
        """What the student should change in the app, or the presenter on the Connect tab,
        for a right pose: a sensor missing for the tilt, a convention that is a guess."""
        out = []
        src = self._sources.get("ACC")
        if src == "gravity":
            out.append("the tilt comes from the phone's Gravity alone: tick Accelerometer too, "
                       "or no shake reaches the filters")
        elif src is None and self.unused.get("accelerometer"):
            out.append("no tilt: Accelerometer without Gravity (the phone removes gravity from "
                       "it): tick Gravity in the app")
        if self._override is None and self.platform != "android" and self._released:
            if self._conv_source == "assumed":
                out.append("the sign convention is a guess (no calibrated magnetometer or raw "
                           "accelerometer to tell): if the phone shows upside down, pick the sign "
                           "convention on the Connect tab")
            elif not self._conv_strong:
                out.append("the sign convention comes from the field's dip, which assumes the "
                           "northern hemisphere: south of the magnetic equator, pick it on the "
                           "Connect tab")
        return out

    def withheld(self) -> dict[str, str]:
        """The sensors the app sends and this stream holds back, with why: ``orientation``
        (ORI) until its convention is checked, or for good once it failed the check. Not
        once the app has stopped sending it (:data:`~app.sources.ordering.STOPPED_S` behind
        the other sensors): that is a sensor that stopped."""
        if "ORI" not in self._sources or self.ori.chosen is not None or self._ori_last_ms is None:
            return {}
        if self._last_ms is not None and self._last_ms - self._ori_last_ms > STOPPED_S * 1000.0:
            return {}
        return {"ORI": self._ori_message()}

    def _ori_message(self) -> str:
        """The orientation check in words; without a magnetometer it cannot run, and
        holding the phone still does not help (it said so for good)."""
        if self.ori.chosen is None and "MAG" not in self._sources and self.messages >= NO_ORI_AFTER:
            return "not checked: it needs the magnetometer (tick Magnetometer in the app's sensors)"
        return self.ori.message()

    def status(self) -> dict:
        """A JSON-safe summary for the page and ``GET /api/connect``."""
        off = float(np.median(self._offsets)) if self._offsets else None
        dev, ses = self._key if self._key else (None, None)
        sources = dict(self._sources)
        if "ORI" in sources and self.ori.chosen is None:
            sources["ORI"] = None
        ori = {**self.ori.status(), "message": self._ori_message()}
        if "ORI" not in self._sources and sources and self.messages >= NO_ORI_AFTER:
            # holding the phone still cannot help: the app sends none
            ori = {**ori, "state": "absent",
                   "message": "no Orientation readings: tick Orientation in the app's sensors "
                              "to compare with the phone's own estimate"}
        return {
            "platform": self.platform or "unknown",
            "platform_reason": self.platform_reason,
            "convention": self.convention,
            "convention_source": self.convention_source,
            "reasons": self._reasons_now(),
            "hints": self.hints(),
            "device_id": _short(dev),
            "session_id": _short(ses),
            "sessions": self.sessions,
            "messages": self.messages,
            "gaps": self.gaps,
            "out_of_order": self.out_of_order,
            "late": self.late, "late_readings": self.late_readings,
            "duplicates": self.duplicates,
            "held": len(self._held),
            "rejected": dict(self.rejected),
            "ignored": dict(self.ignored),
            "invalid": dict(self.invalid),
            "unused": dict(self.unused),
            "rates_hz": self.rates(),
            "last_sample_s": None if self._last_ms is None else self._last_ms / 1000.0,
            "clock_offset_s": None if off is None or not math.isfinite(off) else round(off, 3),
            "orientation": ori,
            "sources": sources,
        }
