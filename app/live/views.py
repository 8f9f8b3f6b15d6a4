"""Read models: what the scene, the GUI and the API read (and nothing else).

- :class:`Snapshot`: what the 3D scene draws;
- :func:`state`: GET /api/state (see :class:`app.server.models.State`);
- :func:`estimator_state` with :func:`app.live.ensemble.decision`: one instance's read-out;
- :class:`Latency` and :func:`percentiles`: GET /api/stats.

Pure functions of the live core; JSON-safe (NaN and inf become None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.estimators import REASON_TEXT, Diagnostics, Reason, StepFlags
from app.estimators.base import is_rejected
from app.quaternion import angle_between, q2euler

from app.live.ensemble import Ensemble
from app.live.session import Session


class CoreReadout(Protocol):
    """What the read models read of the live core (:class:`app.live.core.LiveCore` is
    one): the views are defined on this, so ``core`` imports ``views`` and not back."""
    ensemble: Ensemble
    session: Session | None
    t_sent: float | None
    last_vec: list

    def truth_q(self) -> np.ndarray | None: ...
    def source_kind(self) -> str: ...
    def status_text(self) -> str: ...
    def counts(self) -> dict[str, Any]: ...


def num(x) -> float | None:
    """A JSON-safe float (NaN and inf become None)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def qlist(q) -> list[float] | None:
    return None if q is None else [float(v) for v in q]


def json_safe(x):
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (float, np.floating)):
        return num(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


REFERENCE_UNUSED = "not used (the phone's own estimate uses none of the samples)"


def decision(f: StepFlags | None, sensor: str, reference: bool = False) -> dict[str, Any]:
    """How an estimator treated the last sample of ``sensor`` (the API's Decision);
    ``reference``: the phone's own estimate, which uses no sample (not "switched off")."""
    if f is None:
        return {"reason": "absent", "text": REASON_TEXT[Reason.ABSENT], "rejected": False,
                "value": None, "nis": None, "t": None}
    r: Reason = getattr(f, sensor)
    text = REFERENCE_UNUSED if reference and r == Reason.DISABLED else REASON_TEXT[r]
    return {"reason": r.label, "text": text, "rejected": is_rejected(r),
            "value": num(getattr(f, f"{sensor}_value", None)),
            "nis": num(getattr(f, f"{sensor}_nis", None)), "t": num(f.t)}



@dataclass
class Snapshot:
    """What the scene draws: the state after the last processed sample."""
    t: float | None
    primary: str
    q: np.ndarray
    initialized: bool
    phone_q: np.ndarray | None
    truth_q: np.ndarray | None
    cov: np.ndarray | None
    acc: np.ndarray | None          # last accelerometer sample (sensor frame)
    mag: np.ndarray | None          # last magnetometer sample (sensor frame)
    acc_flags: StepFlags | None     # primary's flags of the last accelerometer row
    mag_flags: StepFlags | None
    rest: bool
    diag: Diagnostics


def snapshot(core: CoreReadout) -> Snapshot:
    b = core.ensemble
    inst = b.instances[b.primary]
    est = inst.estimator
    return Snapshot(t=core.t_sent, primary=b.primary, q=est.q, initialized=est.initialized,
                    phone_q=b.phone_q, truth_q=core.truth_q(), cov=est.attitude_cov(),
                    acc=core.last_vec[1], mag=core.last_vec[2],
                    acc_flags=inst.flags("acc"), mag_flags=inst.flags("mag"),
                    rest=inst.rest, diag=est.diagnostics())


def error_deg(qa, qb) -> float | None:
    """Formula (2c) between two orientations, in degrees (None if either is missing)."""
    if qa is None or qb is None:
        return None
    return num(math.degrees(angle_between(qa, qb)))


def estimator_state(core: CoreReadout, name: str, phone_q=None, truth_q=None) -> dict[str, Any]:
    inst = core.ensemble.instances[name]
    est = inst.estimator
    q = est.q
    return {"q": qlist(q), "euler_deg": [float(np.degrees(a)) for a in q2euler(q)],
            "base": inst.base, "initialized": bool(est.initialized),
            "error_to_phone_deg": error_deg(phone_q, q),
            "error_to_truth_deg": error_deg(truth_q, q),
            "acc": decision(inst.flags("acc"), "acc", core.ensemble.is_reference(name)),
            "mag": decision(inst.flags("mag"), "mag", core.ensemble.is_reference(name)),
            "gyr_bias": None if est.gyr_bias is None else qlist(est.gyr_bias),
            "step_errors": inst.step_errors, "restored": inst.restored}


def state(core: CoreReadout) -> dict[str, Any]:
    """GET /api/state."""
    b = core.ensemble
    phone_q = b.phone_q
    truth_q = core.truth_q()
    ests = {n: estimator_state(core, n, phone_q, truth_q) for n in b.names}
    prim = ests[b.primary]
    inst = b.instances[b.primary]
    est = inst.estimator
    cov = est.attitude_cov()
    sigma = None if cov is None else [num(math.degrees(math.sqrt(max(c, 0.0)))) for c in np.diag(cov)]
    s = core.session
    return {
        "t": core.t_sent, "source": core.source_kind(), "status": core.status_text(),
        # a connected phone that went quiet: seconds since its last samples; else null
        "silent_s": None if s is None else num(s.silent()),
        "primary": b.primary, "q": prim["q"], "euler_deg": prim["euler_deg"],
        "initialized": prim["initialized"],
        "phone_q": qlist(phone_q),
        "phone_euler_deg": None if phone_q is None else [float(np.degrees(a)) for a in q2euler(phone_q)],
        "truth_q": qlist(truth_q),
        "error_to_phone_deg": prim["error_to_phone_deg"],
        "error_to_truth_deg": prim["error_to_truth_deg"],
        "acc_rejected": prim["acc"]["rejected"], "mag_rejected": prim["mag"]["rejected"],
        "acc": prim["acc"], "mag": prim["mag"],
        "standstill": inst.rest,
        "sigma_deg": sigma,
        "diagnostics": json_safe(est.diagnostics().as_dict()),
        "rates_hz": {k: num(v) for k, v in s.rates().items()} if s else {},
        # sensors the phone sends that its source holds back, and why (not stopped)
        "withheld": dict(s.withheld) if s else {},
        "counts": core.counts(),
        "clock_offsets_s": s.clock_offsets if s else {},
        "estimators": ests,
    }


class Tape:
    """The last ``capacity`` rows of ``width`` floats, in one array made (and touched)
    up front: a deque of tuples grew the server's memory by ~30 MB over the first half
    hour of a stream (a tuple and three floats a chunk, 100 chunks a second) and made
    :meth:`Latency.figures` convert 200,000 tuples on the event loop. ``np.asarray(tape)``
    gives the rows kept, oldest first."""

    def __init__(self, capacity: int, width: int = 1):
        self.data = np.full((capacity, width), np.nan)
        self.n = 0                   # rows appended in total

    def append(self, row) -> None:
        self.data[self.n % self.data.shape[0]] = row
        self.n += 1

    def clear(self) -> None:
        self.n = 0

    def __len__(self) -> int:
        return min(self.n, self.data.shape[0])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        cap = self.data.shape[0]
        out = self.data[:self.n] if self.n <= cap else \
            np.roll(self.data, -(self.n % cap), axis=0)
        out = out[:, 0] if out.shape[1] == 1 else out
        return out.astype(dtype or float, copy=True)


class Latency:
    """Per processed chunk: (arrival -> pose queued, arrival -> taken, n samples), and how
    late the display timers ran (the event loop's lag). Written by the async shell."""

    def __init__(self, maxlen: int = 200_000):
        self.chunks = Tape(maxlen, 3)
        self.loop_lag = Tape(maxlen // 2)
        self.backlog_max = 0
        self.batches = 0

    def clear(self) -> None:
        self.chunks.clear()
        self.loop_lag.clear()
        self.backlog_max = 0

    def figures(self) -> dict[str, Any]:
        """Median, p99 and max (ms) of the per-sample latency, the wait and the loop lag
        (vectorised: this runs on the event loop)."""
        chunks = np.array(self.chunks, dtype=float).reshape(-1, 3)
        counts = chunks[:, 2].astype(np.int64)
        return {"latency_ms": percentiles(chunks[:, 0], counts),
                "wait_ms": percentiles(chunks[:, 1], counts),
                "loop_lag_ms": percentiles(np.array(self.loop_lag, dtype=float))}


def percentiles(x: np.ndarray, counts: np.ndarray | None = None) -> dict[str, Any]:
    """Median, 99th percentile and max of durations in seconds, in ms; ``counts``: how
    many times each value counts (one per sample of a chunk), the figures being those
    of the values repeated so (``np.percentile``'s linear interpolation), without
    building that array (GET /api/stats runs on the event loop)."""
    x = np.asarray(x, dtype=float)
    if counts is None:
        counts = np.ones(x.size, dtype=np.int64)
    keep = counts > 0
    x, counts = x[keep], counts[keep]
    n = int(counts.sum())
    if not n:
        return {"n": 0, "median": None, "p99": None, "max": None}
    order = np.argsort(x, kind="stable")
    ms = x[order] * 1e3
    ends = np.cumsum(counts[order])          # the k-th value (0-based) is ms[first end > k]

    def pct(p: float) -> float:
        h = (n - 1) * p / 100.0
        lo = math.floor(h)
        a, b = ms[np.searchsorted(ends, [lo, min(lo + 1, n - 1)], side="right")]
        return a + (b - a) * (h - lo)

    return {"n": n, "median": num(pct(50.0)), "p99": num(pct(99.0)), "max": num(ms[-1])}
