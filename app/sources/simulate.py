"""A simulated phone with ground truth: the lab's scenes, pure numpy, no I/O.

The phone starts lying flat, screen up, its top pointing 30° east of north, and goes
through the lab manual's experiments one scene after the other:

========== =================================================================
``still``        lying still (the gyroscope bias is all the gyroscope sees)
``turn_x``       a slow turn to 90° about the sensor's x axis and back
``turn_y``       likewise about y
``turn_z``       likewise about z (heading only: the magnetometer's job)
``shake``        shaken by hand: ±12 m/s² along east and ±6 m/s² up and down
``magnet``       a magnet passes by (up to +80 µT towards east, for ~2 s)
``gyro_dropout`` a turn about z and back while the gyroscope sends nothing
========== =================================================================

Every scene returns to the base orientation, so the scenes loop seamlessly
(:func:`stream` is endless). The sensors follow the Sensor Fusion app's conventions
(see ``shared/protocols/sensorfusion-app.md``): ACC is specific force in m/s²
(≈ +9.81 along the axis pointing up at rest), GYR rad/s with a constant bias and
white noise, MAG µT (Earth field 50 µT with a dip of 65°, plus noise), ORI the
phone's own estimate (the truth turned by a slowly wandering error of about 1°).
ACC, GYR and ORI run at 100 Hz, MAG at 50 Hz; timestamps are integer milliseconds of
a phone's boot clock, and each sensor samples at its own offset within the period.
As a real sensor's, each GYR, ACC and MAG sample stands for its period and is stamped at its
end: it is the mean of the sensor's value over the period before its stamp (``SUBSAMPLES``
points), so it lags the truth at its stamp by half a period, the lag the filter's terms
``mag_delay`` and ``acc_delay_periods`` turn forward. ORI, the phone's own estimate, is the
value at its stamp.

Use :func:`simulate` for a finite run with its truth (tests, benchmarks) and
:func:`stream` for the dashboard's endless demo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from app.params import GRAVITY
from app.quaternion import quat_from_rotvec_many, quat_mul_many, rotate_inv_many
from app.sources.sensorfusion import format_line


SCENES = ("still", "turn_x", "turn_y", "turn_z", "shake", "magnet", "gyro_dropout")
SCENE_DURATION_S = {"still": 4.0, "turn_x": 6.0, "turn_y": 6.0, "turn_z": 6.0, "shake": 4.0,
                    "magnet": 6.0, "gyro_dropout": 6.0}

# A GYR, ACC or MAG sample is the mean over its period of this many evenly spaced values (the
# midpoint rule): the error of the mean is below 0.1 % of the signal's change over a period
SUBSAMPLES = 8


@dataclass(frozen=True)
class SimConfig:
    """What the simulated phone is like (SI units)."""
    gyr_bias: tuple = (0.03, -0.02, 0.04)       # rad/s
    gyr_noise: float = 0.005                    # rad/s per sample
    acc_noise: float = 0.05                     # m/s² per sample
    mag_noise: float = 0.4                      # µT per sample
    ori_error_deg: float = 1.0                  # amplitude of the phone's own error
    field_ut: float = 50.0                      # Earth field strength
    dip_deg: float = 65.0                       # inclination (field points down, north)
    heading_deg: float = 30.0                   # base heading: top of the phone, east of north
    acc_period_ms: int = 10                     # 100 Hz
    gyr_period_ms: int = 10
    ori_period_ms: int = 10
    mag_period_ms: int = 20                     # 50 Hz
    boot_ms: int = 164_805_773                  # phone clock at the start
    scenes: tuple = SCENES
    durations: dict = field(default_factory=lambda: dict(SCENE_DURATION_S))

    def mag_world(self) -> np.ndarray:
        d = math.radians(self.dip_deg)
        return self.field_ut * np.array([0.0, math.cos(d), -math.sin(d)])

    def base_q(self) -> np.ndarray:
        """Flat, screen up, top pointing ``heading_deg`` east of north (a turn about -z)."""
        a = -math.radians(self.heading_deg)
        return np.array([math.cos(a / 2), 0.0, 0.0, math.sin(a / 2)])


# ----------------------------------------------------------------- the scenes

def _bump(u: np.ndarray) -> np.ndarray:
    """0 -> 1 -> 0 smoothly over u in [0, 1] (zero slope at both ends)."""
    return 0.5 * (1.0 - np.cos(2.0 * np.pi * u))


def _bump_rate(u: np.ndarray, T: float) -> np.ndarray:
    return np.pi / T * np.sin(2.0 * np.pi * u)


def _scene_motion(name: str, tau: np.ndarray, T: float):
    """Body-frame rotation vector, its rate (rad/s), world linear acceleration (m/s²) and
    world field disturbance (µT) at times ``tau`` (s) into a scene of length ``T``."""
    n = tau.shape[0]
    rv = np.zeros((n, 3))
    w = np.zeros((n, 3))
    a_lin = np.zeros((n, 3))
    b_dist = np.zeros((n, 3))
    u = tau / T
    axis = {"turn_x": 0, "turn_y": 1, "turn_z": 2, "gyro_dropout": 2}.get(name)
    if axis is not None:
        amp = np.pi / 2 if name != "gyro_dropout" else np.pi / 3
        rv[:, axis] = amp * _bump(u)
        w[:, axis] = amp * _bump_rate(u, T)
    elif name == "shake":
        env = np.sin(np.pi * u) ** 2
        f = 2.5
        # a hand's shake: strong enough that |a| leaves report A's 0.75 g - 1.25 g band
        a_lin[:, 0] = 12.0 * env * np.sin(2 * np.pi * f * tau)
        a_lin[:, 2] = 6.0 * env * np.sin(2 * np.pi * f * tau + np.pi / 3)
        wob = math.radians(4.0)
        rv[:, 1] = wob * env * np.sin(2 * np.pi * f * tau)
        denv = 2 * np.sin(np.pi * u) * np.cos(np.pi * u) * np.pi / T
        w[:, 1] = wob * (denv * np.sin(2 * np.pi * f * tau)
                         + env * 2 * np.pi * f * np.cos(2 * np.pi * f * tau))
    elif name == "magnet":
        b_dist[:, 0] = 80.0 * np.exp(-0.5 * ((tau - 0.5 * T) / 0.5) ** 2)
    elif name != "still":
        raise ValueError(f"unknown scene {name!r} (known: {', '.join(SCENES)})")
    return rv, w, a_lin, b_dist


class Simulation:
    """The scene schedule of one simulated phone: the truth and the sensors at any time.

    Times ``t`` are seconds since the start of the simulation; the phone's clock is
    ``time_ms = boot_ms + round(1000 t)``. The schedule repeats after ``period`` s.
    """

    def __init__(self, config: SimConfig | None = None, scenes: tuple | None = None):
        self.config = config or SimConfig()
        self.scenes = tuple(scenes or self.config.scenes)
        for s in self.scenes:
            if s not in SCENES:
                raise ValueError(f"unknown scene {s!r} (known: {', '.join(SCENES)})")
        self.durations = np.array([self.config.durations[s] for s in self.scenes])
        self.starts = np.concatenate([[0.0], np.cumsum(self.durations)[:-1]])
        self.period = float(np.sum(self.durations))
        self._q0 = self.config.base_q()
        self._m_world = self.config.mag_world()

    def scene_at(self, t) -> np.ndarray:
        """Index into ``scenes`` of the scene running at each time."""
        tt = np.mod(np.atleast_1d(np.asarray(t, float)), self.period)
        return np.clip(np.searchsorted(self.starts, tt, side="right") - 1, 0, len(self.scenes) - 1)

    def motion(self, t):
        """(q (N,4), ω body (N,3), linear acceleration world (N,3), field disturbance (N,3))."""
        t = np.atleast_1d(np.asarray(t, float))
        idx = self.scene_at(t)
        tau = np.mod(t, self.period) - self.starts[idx]
        n = t.shape[0]
        rv = np.zeros((n, 3)); w = np.zeros((n, 3)); a = np.zeros((n, 3)); b = np.zeros((n, 3))
        for k, name in enumerate(self.scenes):
            sel = idx == k
            if np.any(sel):
                rv[sel], w[sel], a[sel], b[sel] = _scene_motion(name, tau[sel], self.durations[k])
        q = quat_mul_many(self._q0, quat_from_rotvec_many(rv))
        q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
        return q, w, a, b

    def truth(self, t) -> np.ndarray:
        """True orientation (N,4) [w,x,y,z], sensor to world, at times ``t`` (s)."""
        return self.motion(t)[0]

    def sensed(self, t, period: float):
        """What the sensors read at stamps ``t`` (s), each the mean over the ``period`` (s)
        before its stamp, noise-free: (rate (N,3) rad/s, specific force (N,3) m/s², field
        (N,3) µT), all in the sensor frame."""
        t = np.atleast_1d(np.asarray(t, float))
        n = t.shape[0]
        offsets = period * (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES
        tt = (t[:, None] - offsets[None, :]).reshape(-1)
        q, w, a_lin, b = self.motion(tt)
        f = rotate_inv_many(q, a_lin + np.array([0.0, 0.0, GRAVITY]))
        m = rotate_inv_many(q, self._m_world + b)
        mean = lambda x: x.reshape(n, SUBSAMPLES, 3).mean(axis=1)  # noqa: E731
        return mean(w), mean(f), mean(m)

    def gyro_absent(self, t) -> np.ndarray:
        idx = self.scene_at(t)
        names = np.array(self.scenes, dtype=object)
        return names[idx] == "gyro_dropout"

    def samples(self, t_start: float, t_end: float, rng: np.random.Generator):
        """Sensor samples with ``t_start <= t < t_end`` as time-sorted (time_ms, tag, values)."""
        c = self.config
        out = []
        start_ms = int(math.ceil(t_start * 1000.0))
        end_ms = int(math.ceil(t_end * 1000.0))
        for tag, period, phase in (("GYR", c.gyr_period_ms, 0), ("ACC", c.acc_period_ms, 2),
                                   ("MAG", c.mag_period_ms, 5), ("ORI", c.ori_period_ms, 7)):
            k0 = -(-(start_ms - phase) // period)
            ms = np.arange(k0 * period + phase, end_ms, period)
            ms = ms[ms >= start_ms]
            if ms.size == 0:
                continue
            t = ms / 1000.0
            if tag == "GYR":
                keep = ~self.gyro_absent(t)
                ms, t = ms[keep], t[keep]
                w = self.sensed(t, period / 1000.0)[0]
                vals = w + np.asarray(c.gyr_bias) + rng.normal(0.0, c.gyr_noise, w.shape)
            elif tag == "ACC":
                f = self.sensed(t, period / 1000.0)[1]
                vals = f + rng.normal(0.0, c.acc_noise, f.shape)
            elif tag == "MAG":
                m = self.sensed(t, period / 1000.0)[2]
                vals = m + rng.normal(0.0, c.mag_noise, m.shape)
            else:  # ORI: truth with a slowly wandering error, as a phone's own filter
                q = self.truth(t)
                amp = math.radians(c.ori_error_deg)
                err = amp * np.stack([np.sin(0.31 * t), np.cos(0.23 * t), np.sin(0.17 * t + 1.0)], -1)
                vals = quat_mul_many(quat_from_rotvec_many(err), q)
                vals = vals * np.where(vals[:, :1] < 0, -1.0, 1.0)
            for m, v in zip((c.boot_ms + ms).tolist(), vals.tolist()):
                out.append((m, tag, tuple(v)))
        out.sort(key=lambda s: s[0])
        return out


@dataclass
class SimResult:
    """A finite simulation: the samples as the phone would send them, and the truth."""
    samples: list                 # (time_ms, tag, values) in time order
    sim: Simulation
    t_end: float

    @property
    def boot_ms(self) -> int:
        return self.sim.config.boot_ms

    def truth(self, t) -> np.ndarray:
        """True orientation (N,4) at times ``t`` in s since the start."""
        return self.sim.truth(t)

    def truth_at_ms(self, time_ms) -> np.ndarray:
        """True orientation (N,4) at phone-clock times (ms, as in the samples)."""
        return self.sim.truth((np.asarray(time_ms, float) - self.boot_ms) / 1000.0)

    def lines(self) -> list[str]:
        return [format_line(*s) for s in self.samples]


def simulate(scenes: tuple = SCENES, *, duration_s: float | None = None, seed: int = 0,
             config: SimConfig | None = None) -> SimResult:
    """Simulate ``scenes`` once (or for ``duration_s`` s, looping). Returns the samples
    ``(time_ms, tag, values)`` in time order and the truth (``result.truth(t)``,
    ``result.truth_at_ms(time_ms)``)."""
    sim = Simulation(config, scenes)
    t_end = sim.period if duration_s is None else float(duration_s)
    rng = np.random.default_rng(seed)
    return SimResult(samples=sim.samples(0.0, t_end, rng), sim=sim, t_end=t_end)


def stream(seed: int = 0, config: SimConfig | None = None, chunk_s: float = 0.5
           ) -> Iterator[tuple[int, str, tuple]]:
    """Endless demo stream: the scenes in a loop, in time order, time continuing."""
    sim = Simulation(config)
    rng = np.random.default_rng(seed)
    t = 0.0
    while True:
        yield from sim.samples(t, t + chunk_s, rng)
        t += chunk_s


__all__ = ["SCENES", "SimConfig", "Simulation", "SimResult", "simulate", "stream"]
