"""phyphox (RWTH Aachen) as a source: its network push, its experiment file and (in
:mod:`.phyphox_poll`) its remote-access poller. See ``shared/protocols/phyphox.md``.

Two ways in, both ending in :class:`~app.sources.samples.Sample` objects:

- **push** (the phone is the HTTP client): :func:`experiment_xml` writes a ``.phyphox``
  file whose ``<network>`` block POSTs the new samples (``keep="false"``) as a JSON
  object every ``interval`` seconds; one :class:`PhyphoxPushStream` per phone decodes
  those bodies (:meth:`PhyphoxPushStream.decode`), drops what it has already seen,
  counts reordered and lost POSTs and notices a new experiment session;
- **poll** (the phone is the HTTP server): :class:`~app.sources.phyphox_poll.PhyphoxPoller`
  (importable from here too) reads ``/config`` and polls ``/get`` incrementally.

Both share :func:`buffers_to_samples`: phyphox buffers (lists of numbers or ``null``)
to samples, skipping and counting what no phone can read.

How the server drives the push (one :class:`PhyphoxPushStream` per phone, e.g. keyed
by the client address)::

    GET  /orientlab.phyphox -> experiment_xml(f"http://{pc_ip}:{port}/phyphox")
                               (application/octet-stream; show its URL as a QR code)
    GET  /privacy           -> a short page: what is sent, where to (shown by the app)
    POST /phyphox           -> body = await request.body()   (cap it, e.g. 16 MB)
                               try: batch = stream.decode(body, time.time())
                               except PhyphoxError as e: count e.reason; answer 400
                               if batch.new_session: reset the orderer / filters
                               feed batch.samples to the SampleOrderer; answer 200 {}
    stream.status()         -> JSON-safe counters, model, clock offset for the UI

Conventions: ``time_ms`` is phyphox experiment time (s) x 1000 as a float, the phone's
own clock; ACC specific force m/s² (phyphox "accelerometer" already is, on both
platforms), GYR rad/s, MAG µT, ORI (w, x, y, z) sensor to ENU with w >= 0 (phyphox
attitude: x, y, z the vector part, ``abs`` the scalar).
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Sequence
from urllib.parse import urlsplit

from app.sources.samples import MAX_TIME_MS, DecodeError, Sample, impossible, quaternion_reading

# phyphox sensor type -> orientlab tag
SENSOR_TAGS: dict[str, str] = {
    "accelerometer": "ACC",
    "gyroscope": "GYR",
    "magnetic_field": "MAG",
    "attitude": "ORI",
}
TAG_SENSORS = {v: k for k, v in SENSOR_TAGS.items()}

# The buffers of the experiment orientlab serves (push and poll): tag -> (t, components);
# ORI's components are (w, x, y, z) = phyphox (abs, x, y, z).
PUSH_BUFFERS: dict[str, tuple[str, tuple[str, ...]]] = {
    "ACC": ("acc_t", ("accX", "accY", "accZ")),
    "GYR": ("gyr_t", ("gyrX", "gyrY", "gyrZ")),
    "MAG": ("mag_t", ("magX", "magY", "magZ")),
    "ORI": ("att_t", ("attW", "attX", "attY", "attZ")),
}
TIMEINFO_KEY = "timeinfo"
MODEL_KEY = "model"
# which phyphox output component each of a tag's values comes from
COMPONENTS: dict[str, tuple[str, ...]] = {
    "ACC": ("x", "y", "z"), "GYR": ("x", "y", "z"), "MAG": ("x", "y", "z"),
    "ORI": ("abs", "x", "y", "z"),
}



class PhyphoxError(DecodeError):
    """Input from phyphox that cannot be used; ``reason`` is a short key for counting,
    the message a short description (never the input itself)."""


@dataclass
class Batch:
    """What one push body (or one poll) gave: samples in time order (stable), and
    whether they start a new experiment session (the consumer resets its state)."""
    samples: list[Sample]
    new_session: bool
    # a push decoder's batch (app.server.phones): phyphox releases no old session's tail
    # with a new one, and drops and counts its stale samples itself (counts["stale"])
    ended = ()
    late = 0


# ------------------------------------------------------------------ experiment file

def _check_url(url: str, what: str) -> tuple[str, str]:
    """(scheme, netloc) of an http(s) URL with a host, else ValueError."""
    try:
        parts = urlsplit(url)
        parts.port   # raises on a bad port
    except ValueError as exc:
        raise ValueError(f"{what} {url[:100]!r} is not a valid URL ({exc})") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"{what} must be an http:// or https:// URL with a host, "
                         f"got {url[:100]!r}")
    return parts.scheme, parts.netloc


def experiment_xml(push_url: str | None, interval_s: float = 0.1,
                   title: str = "orientlab IMU") -> str:
    """The ``.phyphox`` experiment (file format 1.14) orientlab serves: accelerometer
    (with g), gyroscope, magnetometer and attitude (``ignoreUnavailable``), all at
    ``rate="0"`` into unlimited containers named as in :data:`PUSH_BUFFERS`, a small
    live view, and with ``push_url`` a ``<network>`` block that POSTs the new samples
    (``keep="false"``), the time reference and the device model to ``push_url`` every
    ``interval_s`` seconds while measuring (privacy URL ``/privacy`` on the same host).
    Without ``push_url`` the file is for remote access (poll) only."""
    if push_url is not None:
        scheme, netloc = _check_url(push_url, "push_url")
        privacy = f"{scheme}://{netloc}/privacy"
    if not (isinstance(interval_s, (int, float)) and math.isfinite(interval_s)
            and 0.01 <= interval_s <= 60.0):
        raise ValueError(f"interval_s must be between 0.01 and 60 s, got {interval_s!r}")

    root = ET.Element("phyphox", version="1.14", locale="en")
    ET.SubElement(root, "title").text = title
    ET.SubElement(root, "category").text = "orientlab"
    ET.SubElement(root, "description").text = (
        "Accelerometer (with g), gyroscope, magnetometer and the phone's attitude for "
        "orientlab" + (", sent to the PC while measuring." if push_url else "."))
    containers = ET.SubElement(root, "data-containers")
    names: list[str] = []
    for tag in ("ACC", "GYR", "MAG", "ORI"):
        tname, comps = PUSH_BUFFERS[tag]
        for name in (tname, *comps):
            ET.SubElement(containers, "container", size="0").text = name
            names.append(name)
    inp = ET.SubElement(root, "input")
    for tag in ("ACC", "GYR", "MAG", "ORI"):
        tname, comps = PUSH_BUFFERS[tag]
        attrs = {"type": TAG_SENSORS[tag], "rate": "0"}
        if tag == "ORI":
            attrs["ignoreUnavailable"] = "true"
        sensor = ET.SubElement(inp, "sensor", attrs)
        for comp, name in zip(COMPONENTS[tag], comps):
            ET.SubElement(sensor, "output", component=comp).text = name
        ET.SubElement(sensor, "output", component="t").text = tname
    views = ET.SubElement(root, "views")
    view = ET.SubElement(views, "view", label="Live")
    for label, buf, prec, unit in (("acc z", "accZ", "2", "m/s²"),
                                   ("gyr z", "gyrZ", "3", "rad/s"),
                                   ("mag z", "magZ", "1", "µT")):
        value = ET.SubElement(view, "value", label=label, precision=prec, unit=unit)
        ET.SubElement(value, "input").text = buf
    export = ET.SubElement(root, "export")
    for tag, set_name in (("ACC", "Accelerometer"), ("GYR", "Gyroscope"),
                          ("MAG", "Magnetometer"), ("ORI", "Attitude")):
        tname, comps = PUSH_BUFFERS[tag]
        s = ET.SubElement(export, "set", name=set_name)
        ET.SubElement(s, "data", name="t (s)").text = tname
        for comp, name in zip(COMPONENTS[tag], comps):
            ET.SubElement(s, "data", name=comp).text = name
    if push_url is not None:
        network = ET.SubElement(root, "network")
        conn = ET.SubElement(network, "connection", {
            "id": "orientlab", "service": "http/post", "address": push_url,
            "conversion": "none", "interval": f"{float(interval_s):g}",
            "autoConnect": "true", "privacy": privacy})
        for name in names:
            ET.SubElement(conn, "send", id=name, type="buffer", keep="false").text = name
        ET.SubElement(conn, "send", id=TIMEINFO_KEY, type="time")
        ET.SubElement(conn, "send", id=MODEL_KEY, type="meta").text = "deviceModel"
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


# ------------------------------------------------------------------ buffers -> samples

def _num(v: Any) -> float | None:
    """A buffer entry as float (NaN for null / iOS's "nan"), None if it is no number."""
    t = type(v)
    if t is float:
        return v
    if t is int:
        try:
            return float(v)
        except OverflowError:          # beyond any float: an impossible reading, counted
            return math.inf if v > 0 else -math.inf
    if v is None:
        return math.nan
    if t is str and v.strip().lower() in ("nan", "-nan"):
        return math.nan
    return None


@dataclass
class Converted:
    """What :func:`buffers_to_samples` made of one sensor's buffers: the samples, how
    many entries it used (the shortest buffer's length) and the last finite time among
    them (the next poll threshold), or None."""
    samples: list[Sample]
    kept: int
    last_t: float | None


def buffers_to_samples(tag: str, t: Sequence, comps: Sequence[Sequence],
                       counts: Counter | None = None) -> Converted:
    """One sensor's phyphox buffers (``t`` in experiment seconds, ``comps`` its value
    buffers in the order of :data:`COMPONENTS` — ORI: abs/w, x, y, z, or x, y, z only)
    to samples. Buffers of unequal length (iOS) are cut to the shortest (counted
    ``truncated``, the dropped entries). Skipped and counted in ``counts``: a time that
    is null/NaN/inf (``bad_time``), a null/NaN value (``null``), an entry that is no
    number (``not_numeric``), inf or a physically impossible value (``impossible``), a
    magnetometer reading exactly 0,0,0 (``mag_zero``: iOS before calibration)."""
    if counts is None:
        counts = Counter()
    n = min([len(t)] + [len(c) for c in comps])
    longest = max([len(t)] + [len(c) for c in comps])
    if longest > n:
        counts["truncated"] += longest - n
    out: list[Sample] = []
    last_t: float | None = None
    quat = tag == "ORI"
    for i in range(n):
        tf = _num(t[i])
        if tf is None or not math.isfinite(tf) or abs(tf) * 1000.0 > MAX_TIME_MS:
            counts["bad_time"] += 1
            continue
        last_t = tf
        vals = []
        bad = None
        for c in comps:
            v = _num(c[i])
            if v is None:
                bad = "not_numeric"
                break
            if v != v:
                bad = "null"
                break
            vals.append(v)
        if bad is None:
            if any(math.isinf(v) for v in vals):
                bad = "impossible"
            elif quat:
                qr = quaternion_reading(vals)
                if qr is None:
                    bad = "impossible"
                else:
                    vals = list(qr)
            elif impossible(tag, vals):
                bad = "impossible"
            elif tag == "MAG" and vals[0] == 0.0 and vals[1] == 0.0 and vals[2] == 0.0:
                bad = "mag_zero"
        if bad is not None:
            counts[bad] += 1
            continue
        out.append(Sample(tf * 1000.0, tag, tuple(vals)))
    return Converted(out, n, last_t)


def time_reference(events: Any) -> tuple[float, float] | None:
    """(systemTime, experimentTime) of the last START event of a phyphox time
    reference (``/time`` or a push's ``type="time"`` events), or None. Experiment
    time t is then phone Unix time ``systemTime + (t - experimentTime)``."""
    if not isinstance(events, list):
        return None
    ref = None
    for ev in events:
        if not isinstance(ev, dict) or ev.get("event") != "START":
            continue
        st, et = _num(ev.get("systemTime")), _num(ev.get("experimentTime"))
        if st is None or et is None or not (math.isfinite(st) and math.isfinite(et)):
            continue
        ref = (st, et)
    return ref


def session_key(events: Any) -> float | None:
    """What identifies an experiment session in the time reference: the systemTime
    of its first START (a clear or a new experiment starts a new list)."""
    if not isinstance(events, list):
        return None
    for ev in events:
        if isinstance(ev, dict) and ev.get("event") == "START":
            st = _num(ev.get("systemTime"))
            if st is not None and math.isfinite(st):
                return st
    return None


# ------------------------------------------------------------------ push

class PhyphoxPushStream:
    """The state of one phone's pushes (``http/post``, ``keep="false"``, the buffers of
    :data:`PUSH_BUFFERS`): one instance per phone, :meth:`decode` per POST body.

    ``counts`` (Counter, by reason): per sample ``duplicate`` (already released:
    overlapping or repeated POST, dropped), ``stale`` (older than the memory of
    released times, ``MEMORY_S`` behind the newest: dropped), ``reordered`` (older than
    the newest released but new: released anyway; the downstream orderer clamps or
    counts them late), ``gap`` (a
    lost POST: every sensor faster than 2 samples per interval jumps by more than half
    an interval + 3 sample periods, where consecutive POSTs are one period apart;
    taken back, ``gap_filled``, when a reordered POST fills the hole), ``truncated``,
    ``null``, ``impossible``, ...
    (:func:`buffers_to_samples`), ``missing_component`` (a sensor's time buffer without
    its values or the other way round), per POST ``posts``, ``sessions``.
    ``model`` the device model, ``clock_offset_s`` phone Unix time of the newest sample
    minus PC time at its arrival (clock offset minus latency), ``phone_now_offset_s``
    the phone's ``now`` minus PC time, ``unix_base_s`` phone Unix time at experiment
    time 0 (for the last START)."""

    # released times remembered per sensor to tell duplicates from reordered samples
    MEMORY_S = 10.0

    def __init__(self, interval_s: float = 0.1,
                 buffers: dict[str, tuple[str, tuple[str, ...]]] | None = None):
        self.interval_s = float(interval_s)
        self.buffers = dict(PUSH_BUFFERS if buffers is None else buffers)
        self.counts: Counter = Counter()
        self.samples_by_tag: Counter = Counter()
        self.model: str | None = None
        self.clock_offset_s: float | None = None
        self.phone_now_offset_s: float | None = None
        self.unix_base_s: float | None = None
        self.last_time_s: float | None = None
        self.last_post_wall: float | None = None
        self._session_key: float | None = None
        self._started = False
        self._new_pending = False
        self._reset()

    # a push decoder's interface (app.server.phones): phyphox's samples are never held back
    waiting = False

    def _reset(self) -> None:
        self._last: dict[str, float] = {}            # newest released time per tag (s)
        self._seen: dict[str, set[float]] = {}        # recent released times per tag
        self._seen_q: dict[str, deque[float]] = {}
        self._period: dict[str, float] = {}           # sample period estimate per tag (s)
        self._gaps: deque[tuple[float, float]] = deque(maxlen=64)

    # ---------------------------------------------------------------- parsing
    @staticmethod
    def read(body: bytes) -> dict:
        """A POST body's JSON object (touches no state: it may run on a worker thread;
        :meth:`take` applies it). Raises :class:`PhyphoxError`, not yet counted
        (:meth:`count_rejected`)."""
        try:
            obj = json.loads(body)
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise PhyphoxError("bad_json", f"body ({len(body)} bytes) is not JSON") from None
        if not isinstance(obj, dict):
            raise PhyphoxError("not_object", f"body is a JSON {type(obj).__name__}, "
                                             "not an object")
        return obj

    @staticmethod
    def _array(obj: dict, name: str) -> list | None:
        if name not in obj:
            return None
        v = obj[name]
        if isinstance(v, list):
            return v
        if v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)):
            return [v]                       # datatype="number": one value
        raise PhyphoxError("bad_buffer", f"buffer {name[:40]!r} is a "
                                         f"{type(v).__name__}, not an array")

    def count_rejected(self, e: PhyphoxError) -> None:
        """Count a POST refused whole (``rejected_<reason>`` in ``counts``)."""
        self.counts[f"rejected_{e.reason}"] += 1

    def decode(self, body: bytes, now: float) -> Batch:
        """Samples of one POST body (``now``: PC wall time of its arrival, s):
        :meth:`read`, then :meth:`take`. Raises :class:`PhyphoxError` for a body that is
        not a JSON object of arrays (answer 400; counted); everything else is counted,
        never raised."""
        try:
            return self.take(self.read(body), now)
        except PhyphoxError as e:
            self.count_rejected(e)
            raise

    def take(self, obj: dict, now: float) -> Batch:
        """Samples of one POST body's object (:meth:`read`); ``new_session`` is True on the
        first batch with samples of each session (the first of the stream too): the
        consumer resets its state then. A part of the wrong type (a buffer that is no
        array, a timeinfo or model of the wrong type) is counted by its reason and left
        out, and the rest of the POST is used: with ``keep="false"`` the phone has cleared
        what it sent. Raises :class:`PhyphoxError` (the POST refused whole) only when such
        a part is all there is."""
        arrays: dict[str, tuple[list, list[list]]] = {}
        bad: list[PhyphoxError] = []
        for tag, (tname, comps) in self.buffers.items():
            try:
                ta = self._array(obj, tname)
                ca = [self._array(obj, c) for c in comps]
            except PhyphoxError as e:       # this sensor's buffers only
                bad.append(e)
                continue
            if ta is None and all(c is None for c in ca):
                continue
            if ta is None or any(c is None for c in ca):
                present = [c for c in ca if c is not None] + ([ta] if ta is not None else [])
                self.counts["missing_component"] += max(len(a) for a in present)
                continue
            arrays[tag] = (ta, ca)
        timeinfo = obj.get(TIMEINFO_KEY)
        if timeinfo is not None and not isinstance(timeinfo, dict):
            bad.append(PhyphoxError("bad_timeinfo", "timeinfo is not an object"))
            timeinfo = None
        model = obj.get(MODEL_KEY)
        if model is not None and not isinstance(model, str):
            bad.append(PhyphoxError("bad_model", "model is not a string"))
            model = None
        if bad and not arrays:
            raise bad[0]
        for e in bad:
            self.counts[e.reason] += 1

        self.counts["posts"] += 1
        self.last_post_wall = now
        by_tag: dict[str, list[Sample]] = {}
        for tag, (ta, ca) in arrays.items():
            by_tag[tag] = buffers_to_samples(tag, ta, ca, self.counts).samples

        # ---- a new session?
        new_session = not self._started
        events = timeinfo.get("events") if timeinfo else None
        key = session_key(events)
        if model:
            model = model[:100]
            if self.model is not None and model != self.model:
                new_session = True
            self.model = model
        if key is not None:
            if self._session_key is not None and abs(key - self._session_key) > 1e-3:
                new_session = True
            self._session_key = key
        first = min((s[0].time_ms for s in by_tag.values() if s), default=None)
        if first is not None and self._last:
            newest = max(self._last.values())
            if first < 1000.0 and newest - first / 1000.0 > 2.0:
                new_session = True     # experiment time back to near 0
        if new_session:
            if self._started:
                self._reset()
            self.counts["sessions"] += 1
            self._started = True
            self._new_pending = True

        # ---- drop what was seen, count reordered and lost POSTs
        out: list[Sample] = []
        jumps: list[tuple[float, float, float]] = []   # (last, first new, threshold)
        for tag, samples in by_tag.items():
            if not samples:
                continue
            last = self._last.get(tag)
            seen = self._seen.setdefault(tag, set())
            seen_q = self._seen_q.setdefault(tag, deque())
            ts = [s.time_ms / 1000.0 for s in samples]
            if len(ts) > 1:
                dts = sorted(b - a for a, b in zip(ts, ts[1:]) if b > a)
                if dts:
                    p = dts[len(dts) // 2]
                    old = self._period.get(tag)
                    self._period[tag] = p if old is None else 0.8 * old + 0.2 * p
            kept_new: list[float] = []
            for s, t in zip(samples, ts):
                if t in seen:
                    self.counts["duplicate"] += 1
                    continue
                if last is not None and t <= last:
                    # released times are remembered for MEMORY_S behind the newest: within
                    # that, a time not seen is new (a POST overtaken, the first one too)
                    if t < last - self.MEMORY_S:
                        self.counts["stale"] += 1
                        continue
                    self.counts["reordered"] += 1
                    self._fill_gap(t)
                else:
                    kept_new.append(t)
                seen.add(t)
                seen_q.append(t)
                out.append(s)
            period = self._period.get(tag, 0.0)
            if last is not None and kept_new and period < 0.5 * self.interval_s:
                # a lost POST leaves a hole of about one interval in every sensor
                # (normally consecutive POSTs are one sample period apart)
                thr = 0.5 * self.interval_s + 3.0 * period
                jumps.append((last, kept_new[0], thr))
            if kept_new:
                newest_new = max(kept_new)
                self._last[tag] = newest_new if last is None else max(newest_new, last)
            newest = self._last.get(tag)
            if newest is not None:
                while seen_q and seen_q[0] < newest - self.MEMORY_S:
                    seen.discard(seen_q.popleft())
        if jumps and all(b - a > thr for a, b, thr in jumps):
            self.counts["gap"] += 1
            self._gaps.append((min(a for a, _, _ in jumps), max(b for _, b, _ in jumps)))

        out.sort(key=lambda s: s.time_ms)
        # the flag goes with the first batch of the session that has samples
        new_session = self._new_pending and bool(out)
        if new_session:
            self._new_pending = False
        for s in out:
            self.samples_by_tag[s.tag] += 1
        if out:
            self.last_time_s = max(self._last.values())

        # ---- clock
        if timeinfo:
            ref = time_reference(events)
            if ref is not None:
                self.unix_base_s = ref[0] - ref[1]
                if self._last:
                    self.clock_offset_s = self.unix_base_s + max(self._last.values()) - now
            pnow = _num(timeinfo.get("now"))
            if pnow is not None and math.isfinite(pnow):
                self.phone_now_offset_s = pnow - now
        return Batch(out, new_session)

    def _fill_gap(self, t: float) -> None:
        for i, (a, b) in enumerate(self._gaps):
            if a < t < b:
                del self._gaps[i]
                self.counts["gap"] -= 1
                self.counts["gap_filled"] += 1
                return

    def flush(self) -> list[Sample]:
        """What it holds when the stream ends: nothing (each POST's samples go at once)."""
        return []

    def due(self, now: float) -> list[Sample]:
        """What it held that is due now: nothing (see :meth:`flush`)."""
        return []

    def status(self) -> dict:
        """JSON-safe summary for the UI."""
        return {"model": self.model, "posts": self.counts["posts"],
                "samples": dict(self.samples_by_tag), "counts": dict(self.counts),
                "last_data_time": self.last_time_s,
                "clock_offset_s": self.clock_offset_s,
                "phone_now_offset_s": self.phone_now_offset_s,
                "unix_base_s": self.unix_base_s}

