"""The Sensor Fusion app's line format (see ``shared/protocols/sensorfusion-app.md``).

Lines in, :class:`~app.sources.samples.Sample` out (and back: :func:`format_line`, the
recordings' format).

One sample per line: ``<time_ms>\\t<TAG>\\t<v1>\\t<v2>...``. :func:`parse_line` turns a
line into a :class:`Sample` or raises :class:`MalformedLine` with the reason; it is
shared by the log reader and the live receiver, so both accept exactly the same input.
"""

from __future__ import annotations

import math

from app.sources.samples import (MAX_TIME_MS, MOTION_TAGS, VALUE_LIMITS, DecodeError, Sample, impossible,
                                 quaternion_reading)

# tag -> accepted value counts (numeric tags) ; None = free text fields
TAG_ARITY: dict[str, tuple[int, ...] | None] = {
    "ACC": (3,), "GYR": (3,), "MAG": (3,),
    "ORI": (4, 3),            # w x y z; rarely x y z only (w = sqrt(1 - x²-y²-z²))
    "RAWGYR": (6, 3), "RAWMAG": (6, 3),   # raw x y z, bias x y z
    "GPS": (3, 2, 4, 5, 6), "PRS": (1,), "LGT": (1,), "PRX": (1,), "TMP": (1,),
    "BAT": (3, 1, 2),
    "RSSWIFI": None, "RSSCELL": None, "RSSBLE": None, "TXT": None,
}


class LineSplitter:
    """Cut a byte stream into the format's lines (``\\n``, ``\\r\\n`` or ``\\r``), holding
    at most ``max_line`` bytes of an unfinished line: shared by the live receiver and
    the log reader, so both frame the input alike.

    A run longer than ``max_line`` without a line end is not a line of this format: it
    is dropped up to the next line end and counted in ``overflows``; the complete lines
    fed with it are still returned (nothing good is lost). What to do about an overflow
    is the caller's policy (the receiver closes that connection, the reader goes on).
    """

    def __init__(self, max_line: int):
        self.max_line = int(max_line)
        self.overflows = 0
        self._buf = b""
        self._skipping = False  # inside an over-long line, dropping up to its end

    @property
    def pending(self) -> bytes:
        """The unterminated tail held so far (the last line of a file without a newline)."""
        return self._buf

    def feed(self, chunk: bytes) -> list[bytes]:
        """The complete lines (without their endings) that ``chunk`` finishes."""
        data = self._buf + chunk if self._buf else chunk
        if b"\r" in data:
            # a lone \r ends a line too; a \r at the very end may be half of \r\n
            tail_cr = data.endswith(b"\r")
            data = data.replace(b"\r\n", b"\n")
            if tail_cr:
                data = data[:-1].replace(b"\r", b"\n") + b"\r"
            else:
                data = data.replace(b"\r", b"\n")
        lines = data.split(b"\n")
        tail = lines.pop()
        if self._skipping:
            if lines:          # the first piece is the end of the over-long line
                lines.pop(0)
                self._skipping = False
            else:              # still inside it
                tail = b""
        if len(tail) > self.max_line:
            self.overflows += 1
            self._skipping = True
            tail = b""
        self._buf = tail
        if any(len(ln) > self.max_line for ln in lines):  # over-long but complete
            n = len(lines)
            lines = [ln for ln in lines if len(ln) <= self.max_line]
            self.overflows += n - len(lines)
        return lines


class MalformedLine(DecodeError):
    """A line that cannot be used; ``reason`` is a short key for counting."""


def _ms(t_f: float):
    """A time stamp as read: whole milliseconds as int (the Sensor Fusion app's own), a
    fraction (a recording of a source with sub-millisecond stamps) kept as float."""
    i = int(t_f)
    return i if i == t_f else t_f


def _float(text: str) -> float:
    # Java float text: 9.81, -0.0, 4.02E-4, NaN, Infinity
    s = text.strip()
    if s in ("Infinity", "+Infinity"):
        return math.inf
    if s == "-Infinity":
        return -math.inf
    return float(s)


# The common line of a live stream: bytes, "<time>\t<ACC|GYR|MAG>\t<x>\t<y>\t<z>"
_VEC3 = {b"ACC": "ACC", b"GYR": "GYR", b"MAG": "MAG"}


def parse_line(line: str | bytes) -> Sample:
    """Parse one line (without or with its line ending). Raises MalformedLine.

    A received line of a 3-vector sensor takes a short path (1500 a second from a phone
    at 500 Hz): the same ``float`` conversions and checks, without decoding, stripping
    and the general arity logic; anything it does not accept outright (a conversion
    that fails, a time or value out of range, another tag or field count) goes the
    general way below, which gives the result or the reason."""
    if type(line) is bytes:
        parts = line.split(b"\t")
        if len(parts) == 5:
            tag = _VEC3.get(parts[1])
            if tag is not None:
                try:
                    t_f = float(parts[0])
                    vals = (float(parts[2]), float(parts[3]), float(parts[4]))
                except ValueError:
                    pass
                else:
                    if abs(t_f) <= MAX_TIME_MS and not impossible(tag, vals):
                        return Sample(_ms(t_f), tag, vals)
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            line = line.decode("utf-8", errors="replace")
    line = line.rstrip("\r\n")
    if not line.strip():
        raise MalformedLine("empty")
    parts = line.split("\t")
    if len(parts) < 2:
        parts = line.split()  # be liberal: spaces instead of tabs
    if len(parts) < 2:
        raise MalformedLine("no_tag", line[:80])
    ts, tag = parts[0].strip(), parts[1].strip()
    try:
        t_f = float(ts)
    except ValueError:
        raise MalformedLine("bad_time", ts[:40]) from None
    if not math.isfinite(t_f) or abs(t_f) > MAX_TIME_MS:
        raise MalformedLine("bad_time", ts[:40])
    time_ms = _ms(t_f)
    if tag not in TAG_ARITY:
        raise MalformedLine("unknown_tag", tag[:40])
    raw = parts[2:]
    arity = TAG_ARITY[tag]
    if arity is None:
        return Sample(time_ms, tag, tuple(raw))
    # drop one trailing empty field (a stray tab at the end of the line)
    if raw and raw[-1].strip() == "":
        raw = raw[:-1]
    if len(raw) not in arity:
        raise MalformedLine("wrong_count", f"{tag} with {len(raw)} values")
    try:
        vals = tuple(_float(v) for v in raw)
    except ValueError:
        raise MalformedLine("not_numeric", f"{tag}: {' '.join(raw)[:60]}") from None
    if tag in VALUE_LIMITS and impossible(tag, vals):
        raise MalformedLine("impossible", f"{tag}: beyond {VALUE_LIMITS[tag]:g} (not a phone's reading)")
    if tag == "ORI":
        q = quaternion_reading(vals)
        if q is None:
            raise MalformedLine("impossible", "ORI: not a unit quaternion (not a phone's attitude)")
        vals = q
    return Sample(time_ms, tag, vals)


def decode_lines(lines, malformed) -> list[Sample]:
    """Lines (bytes or str, without their endings) -> the samples they hold, in order;
    each line that does not parse is counted in ``malformed`` (a Counter) by reason and
    skipped."""
    out: list[Sample] = []
    for line in lines:
        try:
            out.append(parse_line(line))
        except MalformedLine as e:
            malformed[e.reason] += 1
    return out


def format_value(v: float) -> str:
    """A value as the app writes it: up to 9 significant digits (a Java float's text, so a
    phone's reading written again reads back bit for bit), NaN and ±Infinity spelled out."""
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "Infinity" if v > 0 else "-Infinity"
    return f"{v:.9g}"


def format_line(time_ms: int, tag: str, values) -> str:
    """One line of the Sensor Fusion app's format (without the newline); the inverse
    of :func:`parse_line` (a value already text is written as it is)."""
    vals = "\t".join(v if isinstance(v, str) else format_value(float(v)) for v in values)
    i = int(time_ms)
    t = str(i) if i == time_ms else f"{time_ms:.3f}"   # sub-ms stamps: to the µs
    return f"{t}\t{tag}\t{vals}"


def valid_sample_line(line) -> bool:
    """A line holding a usable motion sample (the test for a new connection)."""
    try:
        smp = parse_line(line)
    except MalformedLine:
        return False
    return smp.tag in MOTION_TAGS and all(math.isfinite(v) for v in smp.values)
