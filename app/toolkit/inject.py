"""Virtual disturbances added to a stream's lines: a magnet near the phone, a shake.

A teacher showing how a filter rejects disturbances needs them on demand. The
:class:`Injector` rewrites the stream's lines before anything else reads them (the
parser, the estimators, the plots and the recorder all see the disturbed stream, as
they would see a real magnet), for the live phone, the demo or a replay alike.

**Magnet** (``strength_uT``, ``direction``, ``seconds``, ``frame``): a magnet brought
near the phone adds its own field to the Earth's. A magnet lying on the desk while the
phone turns above it adds a field fixed in the *world* (``frame="world"``, the default):
its reading in the sensor frame turns with the phone, ``Q(q)ᵀ b``, with ``q`` the phone's
orientation (the truth in the demo, else the phone's own estimate ORI, else the primary
estimate: whatever the server hands in). A magnet stuck on the phone or its case moves
with it: fixed in the *sensor* frame (``frame="sensor"``). A dipole's field falls with the
cube of the distance, so a hand bringing it near gives a smooth rise rather than a
step: ``ramp_s`` ramps the field in and out with a raised cosine (default 0: a magnet
put down at its spot at once; 0.5 s is a hand bringing it near, harder for a filter,
since the first microtesla turn the heading before the field strength shows them). It is
added to MAG (and to the raw reading of RAWMAG, its bias left as is). The default
direction, east, is at right angles to the horizontal field, where it turns the apparent
heading most.

**Shake** (``amplitude_ms2``, ``seconds``, ``frequency_hz`` 3 Hz, ``direction``): a hand
shaking the phone back and forth adds a linear acceleration ``A sin(2π f t)`` to the
accelerometer (specific force) without turning it: the orientation is unchanged, so an
estimator that trusts the accelerometer as gravity tilts. ``frame`` as above (default
``sensor``: shaken along the phone's own x axis).

Each disturbance starts at the next line of the sensor it affects (each tag may run on
its own clock, so its window is measured on that tag's clock) and lasts ``seconds`` of
stream time. Its start and end are marked in the stream itself by ``TXT`` lines
(``<time_ms>\\tTXT\\torientlab: magnet ... start``), so a recording holds the marks at their
place; :meth:`Injector.feed` also returns them for the plots.

Bounded: at most :data:`MAX_ACTIVE` disturbances are on at once (:class:`InjectionService`
refuses one more, with a message: a disturbance the class is watching never vanishes
behind its back), and :meth:`Injector.feed` adds them all to a chunk of samples in one
vectorised pass, so the live path's cost per sample does not grow with their number.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from app.sources.samples import Sample
from app.sources.sensorfusion import MalformedLine, decode_lines, format_line, parse_line
from app.quaternion import Q
from app.toolkit.errors import ToolError

KINDS = ("magnet", "shake")
FRAMES = ("world", "sensor")
MAX_SECONDS = 600.0
MAX_ACTIVE = 4          # disturbances on at once; one more is refused (409), see InjectionService
DIRECTIONS = {"east": (1.0, 0.0, 0.0), "west": (-1.0, 0.0, 0.0), "north": (0.0, 1.0, 0.0),
              "south": (0.0, -1.0, 0.0), "up": (0.0, 0.0, 1.0), "down": (0.0, 0.0, -1.0),
              "x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0),
              "-y": (0.0, -1.0, 0.0), "z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}


class InjectError(ValueError):
    """A refused request; ``field`` names the offending key."""

    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


@dataclass(frozen=True)
class Disturbance:
    kind: str                       # "magnet" or "shake"
    magnitude: float                # µT (magnet) or m/s² (shake)
    seconds: float
    direction: tuple[float, float, float]
    frame: str
    ramp_s: float = 0.5
    frequency_hz: float = 3.0

    @property
    def tag(self) -> str:
        return "MAG" if self.kind == "magnet" else "ACC"

    def unit(self, ascii_units: bool = False) -> str:
        if self.kind == "magnet":
            return "uT" if ascii_units else "µT"
        return "m/s2" if ascii_units else "m/s²"

    def describe(self, ascii_units: bool = False) -> str:
        """'magnet 50 µT along [1,0,0] (world frame) for 5 s', as the page and the API say it;
        ``ascii_units``: with 'uT' and 'm/s2', as a mark in a recorded log (the apps' logs are ASCII)."""
        d = ",".join(f"{v:.3g}" for v in self.direction)
        extra = f" {self.frequency_hz:g} Hz" if self.kind == "shake" else ""
        return (f"{self.kind} {self.magnitude:g} {self.unit(ascii_units)}{extra} along [{d}] ({self.frame} "
                f"frame) for {self.seconds:g} s")

    def as_dict(self) -> dict[str, Any]:
        key = "strength_uT" if self.kind == "magnet" else "amplitude_ms2"
        out = {"kind": self.kind, key: self.magnitude, "seconds": self.seconds,
               "direction": list(self.direction), "frame": self.frame, "ramp_s": self.ramp_s}
        if self.kind == "shake":
            out["frequency_hz"] = self.frequency_hz
        return out

    def envelope(self, s: float) -> float:
        """0..1 at ``s`` seconds after the start (raised-cosine ramps at both ends)."""
        if s < 0.0 or s > self.seconds:
            return 0.0
        r = min(self.ramp_s, self.seconds / 2.0)
        if r <= 0.0:
            return 1.0
        edge = min(s, self.seconds - s)
        if edge >= r:
            return 1.0
        return 0.5 - 0.5 * math.cos(math.pi * edge / r)

    def vector(self, s: float) -> np.ndarray:
        """The added vector at ``s`` s after the start, in ``frame`` (µT or m/s²)."""
        a = self.magnitude * self.envelope(s)
        if self.kind == "shake":
            a *= math.sin(2.0 * math.pi * self.frequency_hz * s)
        return a * np.asarray(self.direction, dtype=float)


def _number(body: dict, key: str, lo: float, hi: float, default=None) -> float:
    v = body.get(key, default)
    if v is None:
        raise InjectError(key, "required")
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise InjectError(key, f"must be a finite number, got {v!r}")
    v = float(v)
    if not lo <= v <= hi:
        raise InjectError(key, f"must be in [{lo:g}, {hi:g}], got {v:g}")
    return v


def parse_request(body: dict[str, Any]) -> Disturbance:
    """``{"kind": "magnet", "strength_uT", "direction", "seconds", "frame"?, "ramp_s"?}`` or
    ``{"kind": "shake", "amplitude_ms2", "seconds", "frequency_hz"?, "direction"?,
    "frame"?}`` validated; InjectError names the first bad key. A message quotes at most
    a short excerpt of what was sent (docs/api.md: the input is never echoed)."""

    def said(v: Any) -> str:            # a short excerpt of a value sent, for a message
        r = repr(v)
        return r if len(r) <= 40 else f"{r[:32]}... ({len(r)} characters)"

    if not isinstance(body, dict):
        raise InjectError("body", "expected a JSON object")
    kind = body.get("kind")
    if not isinstance(kind, str) or kind not in KINDS:
        raise InjectError("kind", f"must be one of {', '.join(KINDS)}, got {said(kind)}")
    allowed = {"kind", "seconds", "direction", "frame", "ramp_s"}
    allowed |= {"strength_uT"} if kind == "magnet" else {"amplitude_ms2", "frequency_hz"}
    for k in body:
        if k not in allowed:
            raise InjectError(str(k)[:40], f"unknown key for a {kind} "
                                           f"(known: {', '.join(sorted(allowed))})")
    for k in ("strength_uT", "amplitude_ms2", "seconds", "ramp_s", "frequency_hz"):
        v = body.get(k)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise InjectError(k, f"must be a finite number, got {said(v)}")
    if kind == "magnet":
        mag = _number(body, "strength_uT", 0.0, 5000.0)
        frame = body.get("frame", "world")
        d_default = "east"
    else:
        mag = _number(body, "amplitude_ms2", 0.0, 200.0)
        frame = body.get("frame", "sensor")
        d_default = "x"
    if not isinstance(frame, str) or frame not in FRAMES:
        raise InjectError("frame", f"must be one of {', '.join(FRAMES)}, got {said(frame)}")
    seconds = _number(body, "seconds", 0.05, MAX_SECONDS)
    ramp = _number(body, "ramp_s", 0.0, 10.0, default=0.0 if kind == "magnet" else 0.2)
    freq = _number(body, "frequency_hz", 0.1, 25.0, default=3.0) if kind == "shake" else 3.0
    d = body.get("direction", d_default)
    if isinstance(d, str):
        if d.lower() not in DIRECTIONS:
            raise InjectError("direction", f"a 3-vector or one of {', '.join(DIRECTIONS)}, "
                                           f"got {said(d)}")
        vec = np.array(DIRECTIONS[d.lower()], dtype=float)
    else:
        if isinstance(d, np.ndarray):
            d = d.tolist()
        if not isinstance(d, (list, tuple)) or len(d) != 3 \
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in d):
            raise InjectError("direction", f"a 3-vector or a name, got {said(d)}")
        vec = np.array([float(x) for x in d])
        if not np.all(np.isfinite(vec)):
            raise InjectError("direction", f"a non-zero finite 3-vector, got {said(d)}")
    # the length without overflow: [1e308]*3 squared is inf, and v/inf a zero vector
    scale = float(np.max(np.abs(vec)))
    unit = vec / scale if scale > 0 else vec
    norm = scale * float(np.linalg.norm(unit))
    if not norm >= 1e-9:
        raise InjectError("direction", f"a non-zero finite 3-vector, got {said(d)}")
    vec = unit / np.linalg.norm(unit)
    return Disturbance(kind=kind, magnitude=mag, seconds=seconds,
                       direction=tuple(float(v) for v in vec), frame=frame, ramp_s=ramp,
                       frequency_hz=freq)


@dataclass
class Active:
    d: Disturbance
    id: int
    start_ms: int | None = None         # on the clock of d.tag, set by its first line
    requested_wall: float = 0.0
    ended: bool = False
    frame_used: str = ""                # "sensor" when world was asked but no orientation known
    lines: int = 0

    def info(self) -> dict[str, Any]:
        return {"id": self.id, **self.d.as_dict(), "start_ms": self.start_ms,
                "ended": self.ended, "frame_used": self.frame_used or None, "lines": self.lines}


class Injector:
    """Applies requested disturbances to lines of the app's format.

    ``orientation()`` returns the phone's current orientation (sensor to world, [w,x,y,z])
    or None; it is asked for world-frame disturbances only. Pure apart from that call.
    """

    def __init__(self, orientation: Callable[[], np.ndarray | None] | None = None):
        self.orientation = orientation or (lambda: None)
        self.active: list[Active] = []
        self.history: list[Active] = []
        self._next_id = 1

    def start(self, d: Disturbance, wall: float = 0.0) -> Active:
        a = Active(d=d, id=self._next_id, requested_wall=wall)
        self._next_id += 1
        self.active.append(a)
        self.history.append(a)
        del self.history[:-50]
        return a

    def clear(self) -> None:
        """Stop every disturbance now (a new stream: its clock is another)."""
        for a in self.active:
            a.ended = True
        self.active = []

    @property
    def busy(self) -> bool:
        return bool(self.active)

    def feed(self, samples: list[Sample]) -> tuple[list[Sample], list[dict[str, Any]]]:
        """The samples with the disturbances added, and the marks made (start/end:
        ``{"event", "id", "kind", "time_ms", "text"}``); marks are also TXT samples in
        the returned stream.

        Vectorised over the chunk and over the disturbances: one pass over the samples
        picks those of the tags disturbed, then one set of numpy operations on a
        (disturbances x samples) grid adds them all (a world-frame direction is turned
        into the sensor frame once per chunk: the orientation changes only when the
        estimators step, after this stage). Python work per sample does not grow with the
        number of disturbances on; only a start or an end costs a few lines more."""
        if not self.active:
            return samples, []
        bases = {a.d.tag for a in self.active}
        wanted = bases | {"RAW" + t for t in bases}
        picked: dict[str, list[int]] = {b: [] for b in bases}
        for i, s in enumerate(samples):
            tg = s.tag
            if tg in wanted:
                picked[tg[3:] if tg.startswith("RAW") else tg].append(i)
        rank = {id(a): k for k, a in enumerate(self.active)}
        inserts: list[tuple[int, int, dict[str, Any]]] = []    # (position, active's rank, mark)
        changed: dict[int, np.ndarray] = {}                    # position -> added vector
        turn: list = []                                        # Q(q) of the phone, asked once
        for base, idx in picked.items():
            if not idx:
                continue
            n = len(idx)
            is_base = np.fromiter((samples[i].tag == base for i in idx), bool, n)
            first = int(np.argmax(is_base)) if is_base.any() else -1
            live: list[Active] = []
            lo: list[int] = []
            for a in [a for a in self.active if a.d.tag == base]:
                if a.start_ms is None:
                    if first < 0:
                        continue                    # starts on the calibrated tag's clock
                    a.start_ms = samples[idx[first]].time_ms
                    inserts.append((idx[first], rank[id(a)], self._mark(a, "start", a.start_ms)))
                    lo.append(first)
                else:
                    lo.append(0)
                live.append(a)
            if not live:
                continue
            t = np.fromiter((samples[i].time_ms for i in idx), float, n)
            dur = np.array([a.d.seconds for a in live])[:, None]
            sec = (t[None, :] - np.array([a.start_ms for a in live], float)[:, None]) / 1000.0
            pos = np.arange(n)[None, :]
            after = pos >= np.array(lo)[:, None]
            over = after & is_base[None, :] & (sec > dur)
            ends = over.any(axis=1)
            hi = np.where(ends, over.argmax(axis=1), n)[:, None]
            for k in np.flatnonzero(ends).tolist():
                a = live[k]
                a.ended = True
                self.active.remove(a)
                j = int(hi[k, 0])
                inserts.append((idx[j], rank[id(a)], self._mark(a, "end", samples[idx[j]].time_ms)))
            win = after & (pos < hi) & (sec >= 0.0) & (sec <= dur)
            if not win.any():
                continue
            # the envelope: raised-cosine ramps at both ends (Disturbance.envelope)
            r = np.minimum(np.array([a.d.ramp_s for a in live])[:, None], dur / 2.0)
            edge = np.minimum(sec, dur - sec)
            ramped = 0.5 - 0.5 * np.cos(np.pi * np.clip(edge, 0.0, r) / np.where(r > 0.0, r, 1.0))
            amp = np.where((r > 0.0) & (edge < r), ramped, 1.0) * win
            amp *= np.array([a.d.magnitude for a in live])[:, None]
            shake = np.array([a.d.kind == "shake" for a in live])
            if shake.any():
                f = np.array([a.d.frequency_hz for a in live])[:, None]
                amp = np.where(shake[:, None], amp * np.sin(2.0 * np.pi * f * sec), amp)
            dirs = np.array([a.d.direction for a in live], float)           # (K, 3)
            world = np.array([a.d.frame == "world" for a in live])
            if world.any():
                if not turn:
                    q = self.orientation()
                    ok = q is not None and np.all(np.isfinite(q))
                    turn.append(Q(np.asarray(q, dtype=float)) if ok else None)
                if turn[0] is not None:
                    dirs[world] = dirs[world] @ turn[0]      # rows: (Q(q)^T d)^T
            added = amp.T @ dirs                                             # (N, 3)
            counts = win.sum(axis=1).tolist()
            for k, a in enumerate(live):
                if counts[k]:
                    a.lines += counts[k]
                    if a.d.frame == "world" and turn[0] is not None:
                        a.frame_used = a.frame_used or "world"
                    else:
                        a.frame_used = "sensor"
            for j in np.flatnonzero(win.any(axis=0)).tolist():
                changed[idx[j]] = added[j]
        if not changed and not inserts:
            return samples, []
        out = list(samples)
        for i, v in changed.items():
            s = samples[i]
            vals = list(s.values)
            vals[0] = float(vals[0]) + float(v[0])
            vals[1] = float(vals[1]) + float(v[1])
            vals[2] = float(vals[2]) + float(v[2])
            out[i] = Sample(s.time_ms, s.tag, tuple(vals))
        inserts.sort(key=lambda x: (x[0], x[1]))
        marks = [m for _, _, m in inserts]
        if inserts:
            merged: list[Sample] = []
            prev = 0
            for pos_, _, m in inserts:
                merged.extend(out[prev:pos_])
                merged.append(m["sample"])
                prev = pos_
            merged.extend(out[prev:])
            out = merged
        return out, marks

    def _mark(self, a: Active, event: str, time_ms: int) -> dict[str, Any]:
        text = f"{a.d.describe(ascii_units=True)} {event} (id {a.id})"
        return {"event": event, "id": a.id, "kind": a.d.kind, "time_ms": time_ms,
                "text": text, "sample": Sample(time_ms, "TXT", (f"orientlab: {text}",))}

    def status(self) -> dict[str, Any]:
        return {"active": [a.info() for a in self.active],
                "recent": [a.info() for a in self.history[-10:]]}


def inject_at(lines: list[bytes], request: dict[str, Any], at_s: float,
              orientation: Callable[[], np.ndarray | None] | None = None
              ) -> tuple[list[bytes], float, float]:
    """A whole log (``lines``, in order) with the disturbance ``request`` (as
    ``POST /api/inject`` takes it) started ``at_s`` seconds after its first line: the
    lines (with the marks) and the disturbance's start and end (the phone's clock, s).
    For tests and benchmarks of what a disturbance does to a recording."""
    samples = decode_lines(lines, Counter())
    t0 = samples[0].time_ms
    k = next((i for i, s in enumerate(samples) if s.time_ms - t0 >= at_s * 1000.0), len(samples))
    inj = Injector(orientation)
    head, _ = inj.feed(samples[:k])
    inj.start(parse_request(request))
    tail, marks = inj.feed(samples[k:])
    ends = [m["time_ms"] / 1000.0 for m in marks]
    out = [format_line(s.time_ms, s.tag, s.values).encode() for s in head + tail]
    return out, ends[0], (ends[1] if len(ends) > 1 else math.inf)


def marks_in_log(lines: list[bytes]) -> list[dict[str, Any]]:
    """The orientlab marks (TXT lines) of a log: ``{"time_ms", "text"}``."""
    out = []
    for ln in lines:
        if b"\tTXT\torientlab:" not in ln:
            continue
        try:
            s = parse_line(ln)
        except MalformedLine:
            continue
        out.append({"time_ms": s.time_ms, "text": " ".join(s.values)[len("orientlab: "):]})
    return out


class InjectionService:
    """The live stream's disturbances: requested from the page or the API, added by the
    first of the live core's sample stages (so the recorder and the estimators see the
    disturbed stream), marked for the plots and (:attr:`mark_listeners`) the recording.

    ``core``: the live core (its ``sample_stages``, its session, the orientation a
    world-frame magnet turns with)."""

    def __init__(self, core, max_active: int = MAX_ACTIVE):
        self.core = core
        self.max_active = max_active
        self.injector = Injector(orientation=self.orientation)
        self.marks: list[dict[str, Any]] = []      # injection marks for the plots (stream s)
        self.spans: dict[int, list] = {}           # injection id -> [session, kind, start_s, end_s]
        # (mark, t on the stream's reference clock) -> None: the recorder notes each mark
        self.mark_listeners: list[Callable[[dict[str, Any], float], None]] = []
        self._session = None      # the stream the disturbances on belong to
        core.sample_stages.append(self.stage)

    def _follow(self, session) -> None:
        """A disturbance belongs to the stream it was started on: when another stream is on
        (a phone took over, a replay looped or ended, the demo resumed) every one still on
        ends, rather than reaching into the new stream at its start time (another clock)."""
        if session is not self._session:
            self.injector.clear()
            self._session = session

    def orientation(self) -> np.ndarray | None:
        """The phone's orientation for world-frame disturbances: the truth (demo), else
        the phone's own estimate, else the primary's (before the disturbance shows)."""
        q = self.core.truth_q()
        if q is None:
            q = self.core.ensemble.phone_q
        if q is None:
            b = self.core.ensemble
            est = b.estimator(b.primary)
            q = est.q if est.initialized else None
        return q

    def stage(self, session, samples: list) -> list:
        """The sample stage: the disturbances added, their marks noted."""
        self._follow(session)
        if not self.injector.busy:
            return samples
        samples, marks = self.injector.feed(samples)
        for m in marks:
            self._on_mark(m, session)
        return samples

    def _on_mark(self, m: dict[str, Any], session=None) -> None:
        self.marks.append({**m, "t": m["time_ms"] / 1000.0, "line": None})
        del self.marks[:-40]
        # the span on the stream's reference clock (the plots' time axis): the mark is
        # on the clock of the sensor disturbed, which may run with an offset
        tag = "MAG" if m["kind"] == "magnet" else "ACC"
        off = session.orderer.offsets.get(tag, 0.0) if session is not None else 0.0
        t = m["time_ms"] / 1000.0 - off
        if m["event"] == "start":
            self.spans[m["id"]] = [session, m["kind"], t, math.inf]
            while len(self.spans) > 20:
                del self.spans[next(iter(self.spans))]
        elif m["id"] in self.spans and self.spans[m["id"]][0] is session:
            self.spans[m["id"]][3] = t
        for cb in self.mark_listeners:
            cb(m, t)

    def inject(self, body: dict[str, Any]) -> dict[str, Any]:
        """Start the disturbance ``body`` asks for (:func:`parse_request`); ToolError if
        refused or when no stream is on."""
        try:
            d = parse_request(body)
        except InjectError as e:
            raise ToolError(e.field, e.reason) from None
        if self.core.session is None or not self.core.session.open:
            raise ToolError("kind", "no stream to disturb: connect the phone or run the demo", 409)
        self._follow(self.core.session)
        act = self.injector.active
        if len(act) >= self.max_active:
            # refused rather than replacing the oldest: a disturbance the class is watching
            # never vanishes behind its back, and a burst of clicks changes nothing
            raise ToolError("kind", f"at most {self.max_active} disturbances at once and "
                                    f"{len(act)} are on: wait for one to end (each lasts its "
                                    f"seconds; the longest {max(a.d.seconds for a in act):g} s)",
                            409)
        a = self.injector.start(d, wall=time.time())
        return {"id": a.id, **d.as_dict(), "text": d.describe()}

    def injected_spans(self, session) -> list[tuple[str, float, float]]:
        """``(kind, start_s, end_s)`` of the disturbances injected into ``session``, in
        its stream time (reference clock, as the plots' history); ``end_s`` is inf while
        one is on."""
        return [(k, a, b) for s, k, a, b in self.spans.values() if s is session]

    def size(self, ident: int) -> float:
        """The size (µT or m/s²) of disturbance ``ident``; 0 if forgotten."""
        for a in self.injector.history:
            if a.id == ident:
                return a.d.magnitude
        return 0.0

    def status(self) -> dict[str, Any]:
        return {**self.injector.status(), "max_active": self.max_active, "marks": [
            {k: v for k, v in m.items() if k != "line"} for m in self.marks[-20:]]}
