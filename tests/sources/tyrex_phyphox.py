"""A phones-tyrex trial as phyphox would deliver it (test helper).

:func:`load_trial` turns a trial (npz, ``shared/data/phones-tyrex``) into phyphox
sensor buffers on experiment time (s from the start, each sensor with its own small
time offset as on a phone); :func:`push_bodies` cuts them into the POST bodies the
served experiment sends (``keep="false"``, every ``interval`` s: each body the samples
since the last one, with ``timeinfo`` and ``model``), optionally with an iOS-style
uneven body, a duplicated, a swapped (reordered) or a lost POST.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.sources.phyphox import PUSH_BUFFERS

MODELS = {"Nexus5": "Nexus 5", "iPhone4S": "iPhone4,1", "iPhone5": "iPhone5,2"}
# per sensor offset of its time stamps (s): the sensors of a phone are not in step
OFFSETS = {"ACC": 0.0, "GYR": 0.0013, "MAG": 0.0027, "ORI": 0.0009}
START_UNIX = 1_760_000_111.101


@dataclass
class Trial:
    """Per tag: times (s, experiment time, float64) and values (N x k, float32;
    ORI w, x, y, z as fed to phyphox's abs, x, y, z)."""
    name: str
    model: str
    t: dict[str, np.ndarray]
    v: dict[str, np.ndarray]


def load_trial(path: Path, seconds: float | None = None, t0: float = 0.01) -> Trial:
    d = np.load(path)
    t = np.asarray(d["t"], dtype=float)
    keep = slice(None) if seconds is None else t - t[0] < seconds
    t = t[keep] - t[0] + t0
    vals = {"ACC": d["acc"][keep], "GYR": d["gyr"][keep], "MAG": d["mag"][keep],
            "ORI": d["os_quat"][keep]}
    phone = str(d["phone"])
    return Trial(Path(path).stem, MODELS.get(phone, phone),
                 {tag: t + OFFSETS[tag] for tag in vals},
                 {tag: np.asarray(v, dtype=np.float32) for tag, v in vals.items()})


def _num(x: float):
    x = float(x)
    return None if x != x else x          # NaN -> null, as phyphox writes it


@dataclass
class Pushed:
    bodies: list[bytes]
    # per tag the indices of samples no body carries completely (iOS uneven bodies)
    lost: dict[str, list[int]] = field(default_factory=dict)
    # per body the indices it carries, per tag
    ranges: list[dict[str, tuple[int, int]]] = field(default_factory=list)


def push_bodies(trial: Trial, interval: float = 0.1, *, uneven_every: int = 0,
                start_unix: float = START_UNIX) -> Pushed:
    """The POST bodies of the trial in sending order. ``uneven_every`` = n > 0: every
    n-th body emulates iOS's unlocked snapshot: the accelerometer's x buffer carries
    one sample more than acc_t (the next sample, which then is in no later body)."""
    t_end = max(float(ts[-1]) for ts in trial.t.values())
    n_bodies = int(np.ceil(t_end / interval)) + 1
    starts = {tag: 0 for tag in trial.t}
    out = Pushed([])
    skip: dict[str, int] = {}
    for k in range(n_bodies):
        edge = (k + 1) * interval
        body: dict = {}
        rng = {}
        for tag, (tname, comps) in PUSH_BUFFERS.items():
            ts = trial.t[tag]
            i0 = starts[tag]
            i1 = int(np.searchsorted(ts, edge, side="right"))
            if k == n_bodies - 1:
                i1 = len(ts)
            idx = list(range(i0, i1))
            if tag in skip:
                gone = skip.pop(tag)
                idx = [i for i in idx if i != gone]
            rng[tag] = (i0, i1)
            body[tname] = [_num(ts[i]) for i in idx]
            for j, c in enumerate(comps):
                body[c] = [_num(trial.v[tag][i, j]) for i in idx]
            if (uneven_every and tag == "ACC" and k % uneven_every == uneven_every - 1
                    and i1 < len(ts)):
                body[comps[0]].append(_num(trial.v[tag][i1, 0]))
                out.lost.setdefault(tag, []).append(i1)
                skip[tag] = i1
            starts[tag] = i1
        body["timeinfo"] = {"now": start_unix + edge + 0.003,
                            "events": [{"event": "START", "experimentTime": 0,
                                        "systemTime": start_unix}]}
        body["model"] = trial.model
        out.bodies.append(json.dumps(body).encode())
        out.ranges.append(rng)
    return out


def delivery(bodies: list[bytes], *, duplicate: int | None = None,
             swap: int | None = None, lose: int | None = None) -> list[bytes]:
    """The bodies as the PC receives them: body ``duplicate`` twice (an overlapping
    resend), bodies ``swap`` and ``swap + 1`` in reverse order (slow reply, reordered),
    body ``lose`` never (a failed POST: its samples are gone, keep="false")."""
    order = list(range(len(bodies)))
    if duplicate is not None:
        order.insert(order.index(duplicate) + 1, duplicate)
    if swap is not None:
        i = order.index(swap)
        order[i], order[i + 1] = order[i + 1], order[i]
    if lose is not None:
        order.remove(lose)
    return [bodies[i] for i in order]


def expected(trial: Trial, tag: str, lost: dict[str, list[int]] | None = None):
    """(times in ms, values) of a tag as decoded: NaN rows and lost samples left out,
    ORI with w >= 0."""
    t = trial.t[tag] * 1000.0
    v = trial.v[tag].astype(float)
    ok = ~np.isnan(v).any(axis=1)
    if lost and tag in lost:
        ok[lost[tag]] = False
    v = v[ok]
    if tag == "ORI":
        v = np.where(v[:, :1] < 0, -v, v)
    return t[ok], v
