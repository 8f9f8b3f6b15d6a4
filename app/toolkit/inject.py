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

    @property
    def unit(self) -> str:
        return "uT" if self.kind == "magnet" else "m/s2"

    def describe(self) -> str:
        d = ",".join(f"{v:.3g}" for v in self.direction)
        extra = f" {self.frequency_hz:g} Hz" if self.kind == "shake" else ""
        return (f"{self.kind} {self.magnitude:g} {self.unit}{extra} along [{d}] ({self.frame} "
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
        the returned stream."""
        if not self.active:
            return samples, []
        tags = {a.d.tag for a in self.active}
        tags |= {"RAW" + t for t in tags}
        out: list[Sample] = []
        marks: list[dict[str, Any]] = []
        for s in samples:
            if s.tag not in tags:
                out.append(s)
                continue
            base_tag = s.tag[3:] if s.tag.startswith("RAW") else s.tag
            added = np.zeros(3)
            touched = False
            for a in list(self.active):
                if a.d.tag != base_tag:
                    continue
                if a.start_ms is None:
                    if s.tag != base_tag:       # start on the calibrated tag's clock
                        continue
                    a.start_ms = s.time_ms
                    m = self._mark(a, "start", s.time_ms)
                    marks.append(m)
                    out.append(m["sample"])
                sec = (s.time_ms - a.start_ms) / 1000.0
                if sec > a.d.seconds:
                    if s.tag == base_tag:
                        a.ended = True
                        self.active.remove(a)
                        m = self._mark(a, "end", s.time_ms)
                        marks.append(m)
                        out.append(m["sample"])
                    continue
                if sec < 0.0:
                    continue
                v = a.d.vector(sec)
                if a.d.frame == "world":
                    q = self.orientation()
                    if q is not None and np.all(np.isfinite(q)):
                        v = Q(np.asarray(q, dtype=float)).T @ v
                        a.frame_used = a.frame_used or "world"
                    else:
                        a.frame_used = "sensor"
                else:
                    a.frame_used = "sensor"
                added += v
                a.lines += 1
                touched = True
            if not touched:
                out.append(s)
                continue
            vals = list(s.values)
            for i in range(3):
                vals[i] = float(vals[i]) + float(added[i])
            out.append(Sample(s.time_ms, s.tag, tuple(vals)))
        return out, marks

    def _mark(self, a: Active, event: str, time_ms: int) -> dict[str, Any]:
        text = f"{a.d.describe()} {event} (id {a.id})"
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

    def __init__(self, core):
        self.core = core
        self.injector = Injector(orientation=self.orientation)
        self.marks: list[dict[str, Any]] = []      # injection marks for the plots (stream s)
        self.spans: dict[int, list] = {}           # injection id -> [session, kind, start_s, end_s]
        # (mark, t on the stream's reference clock) -> None: the recorder notes each mark
        self.mark_listeners: list[Callable[[dict[str, Any], float], None]] = []
        core.sample_stages.append(self.stage)

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
        return {**self.injector.status(), "marks": [
            {k: v for k, v in m.items() if k != "line"} for m in self.marks[-20:]]}
