"""The ensemble: every estimator instance, stepped together on the stream's samples.

An **instance** is a named estimator of a base kind (``robust``, ``lab``,
``complementary``, ``phone``): the four builtins carry their kind's name; variants
(``lab-approx``, ``robust-no-rejection``, ...) are added with :meth:`Ensemble.add` and run
beside them. :meth:`Ensemble.step` takes the samples released by a stream, in time order,
and runs them through **each instance's batch run** (``Estimator.run_into``: the
compiled ``robust_run`` for ``robust``, the same code the CLI uses, on the estimator's
state arrays in place), one call per chunk, so the live path costs what the batch path
costs. It returns :class:`Records`: per instance the
estimate and the flag record after every row.

Per row and instance the ensemble keeps, in one compiled call per chunk
(:func:`~app.estimators.base.tally_rows`): how many samples of
each sensor ended with each :class:`~app.estimators.Reason`, and the flag record of the
last row of each sensor (``decision``). It also guards the estimators:

- **a step that raises** is caught: the chunk is stepped again row by row from the last
  good state, the sample that raises is skipped (logged with the sample, counted in
  ``step_errors``) and every other sample is used;
- **a non-finite estimate** after a chunk restores the instance's last good state (kept
  every :data:`GOOD_EVERY_S` seconds) and counts it in ``restored``; the rows from the
  first non-finite one on report the restored estimate.

**The schema** (:class:`EnsembleSchema`, :attr:`Ensemble.schema`): what a change is validated
against (the instances' names, bases, parameter sets, identities, the primary), an
immutable value replaced whole after every add, remove and primary change. Changes are
validated on other threads (the HTTP handlers, viser's GUI threads) while the filter
task may add or remove a variant: they read one schema (never the live ``instances``
dict), so they see the ensemble before or after a change, never half of it; the filter
task's :func:`app.live.changes.apply_change` then refuses a change whose instance is
gone or was replaced meanwhile (its ``uid`` differs).

Pure and synchronous: no asyncio, no I/O; unit-tested without a server.
"""

from __future__ import annotations

import itertools
import logging
import re
import time
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Iterable, Mapping

import numpy as np

from app.estimators import NAMES, REJECTIONS, Estimator, Reason, StepFlags, estimator_class
from app.estimators.base import (F_ACC, F_GYR, F_MAG, F_REST, NFLAGS, new_flags, split_rows,
                               tally_rows)
from app.params import replace_params
from app.quaternion import not_estimated
from app.sources.samples import Sample

log = logging.getLogger("orientlab.ensemble")

SENSORS = ("gyr", "acc", "mag")
FLAG_COL = (F_GYR, F_ACC, F_MAG)
TAG_OF_KIND = ("GYR", "ACC", "MAG", "ORI")                   # row kinds: a sensor, or ORI
KIND_OF_TAG = {tag: k for k, tag in enumerate(TAG_OF_KIND)}
NREASON = len(Reason)
_IS_REJECTION = np.zeros(NREASON, dtype=bool)    # by reason code (a lookup: np.isin is slow)
_IS_REJECTION[[int(r) for r in REJECTIONS]] = True
GOOD_EVERY_S = 1.0          # how often (wall clock) an instance's good state is kept
NAME_RE = re.compile(r"[a-z][a-z0-9_-]{0,39}")


class EnsembleError(ValueError):
    """A refused ensemble operation (bad name, unknown base, builtin removed, ...)."""

    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason


def _no_rows() -> np.ndarray:
    return np.full((3, 1 + NFLAGS), np.nan)


def _flags_of(row: np.ndarray) -> StepFlags | None:
    return None if np.isnan(row[0]) else StepFlags.from_row(row[0], row[1:])


@dataclass
class Instance:
    """One named estimator on the ensemble and what the ensemble keeps about it."""
    name: str
    base: str                       # the estimator kind
    estimator: Estimator
    builtin: bool
    counts: np.ndarray = field(default_factory=lambda: np.zeros((3, NREASON), np.int64))
    # per sensor: time and flag record of the last row holding a sample of it (NaN: none)
    last: np.ndarray = field(default_factory=lambda: _no_rows())
    # per sensor: the same of the last row whose sample a gate refused (the GUI's
    # indicators show its gate and value even when the very last sample was accepted)
    last_rejected: np.ndarray = field(default_factory=lambda: _no_rows())
    step_errors: int = 0
    restored: int = 0
    last_error: str = ""
    _good: Any = None
    _good_at: float = -np.inf
    # this instance's identity: a variant removed and added again under the same name is
    # another instance (a change validated against the first is not applied to it)
    # (the ensemble's counter numbers them: Ensemble._uids)
    uid: int = 0
    # the stream's sensor tags that stopped while it goes on (set by the ensemble): their
    # last decision is no longer news
    stopped: frozenset = frozenset()

    def clear(self) -> None:
        self.counts[:] = 0
        self.last[:] = np.nan
        self.last_rejected[:] = np.nan

    def flags(self, sensor: str) -> StepFlags | None:
        """The flag record of the last row that held a ``sensor`` sample (None: none, or
        the sensor has :attr:`stopped`)."""
        k = SENSORS.index(sensor)
        if TAG_OF_KIND[k] in self.stopped:
            return None
        return _flags_of(self.last[k])

    def rejected_flags(self, sensor: str) -> StepFlags | None:
        """The flag record of the last row whose ``sensor`` sample a gate refused."""
        return _flags_of(self.last_rejected[SENSORS.index(sensor)])

    @property
    def rest(self) -> bool:
        """Standstill, as the last gyroscope row said."""
        return bool(self.last[0, 1 + F_REST] > 0.5)

    def rejections(self, sensor: str) -> int:
        """How many ``sensor`` samples a gate refused so far (see ``is_rejected``)."""
        row = self.counts[SENSORS.index(sensor)]
        return int(sum(row[r] for r in REJECTIONS if r < len(row)))

    def updates(self) -> dict[str, dict[str, int]]:
        """Per sensor, how many samples ended with each reason (nonzero only)."""
        return {s: {Reason(i).label: int(x) for i, x in enumerate(row) if x}
                for s, row in zip(SENSORS, self.counts)}


@dataclass(frozen=True)
class InstanceInfo:
    """One instance as validation sees it (part of a :class:`EnsembleSchema`)."""
    name: str
    base: str
    builtin: bool
    uid: int
    estimator: Estimator            # only its ``params`` are read (a frozen dataclass,
                                    # replaced whole by set_params: one atomic read)

    @property
    def params(self):
        return self.estimator.params


@dataclass(frozen=True)
class EnsembleSchema:
    """An immutable picture of the ensemble for validating changes on any thread (see the
    module doc). The same read methods as :class:`Ensemble` for what validation needs."""
    instances: Mapping[str, InstanceInfo]
    primary: str
    version: int

    @property
    def names(self) -> list[str]:
        return list(self.instances)

    def params_of(self, name: str):
        return self.instances[name].params

    def base_of(self, name: str) -> str:
        return self.instances[name].base

    def is_reference(self, name: str) -> bool:
        """Whether ``name`` is the phone's own estimate (``Estimator.reference``)."""
        return type(self.instances[name].estimator).reference

    def uid_of(self, name: str) -> int:
        return self.instances[name].uid


@dataclass
class Records:
    """What one :meth:`Ensemble.step` made: one row per motion or ORI sample, in order."""
    t: np.ndarray                   # (n,) s
    kind: np.ndarray                # (n,) 0 gyr, 1 acc, 2 mag, 3 ori
    values: np.ndarray              # (n, 4) the sample (3 values + NaN, or ORI's 4)
    q: dict[str, np.ndarray]        # instance -> (n, 4) estimate after each row
    flags: dict[str, np.ndarray]    # instance -> (n, NFLAGS)
    primary: str
    phone_q: np.ndarray             # (n, 4) the phone's own estimate after each row (NaN: none yet)
    n_samples: int                  # samples consumed, ORI and non-motion tags included
    t_last: float | None            # time of the last sample consumed (any tag)

    def __len__(self) -> int:
        return self.t.shape[0]

    @property
    def tags(self) -> list[str]:
        return [TAG_OF_KIND[k] for k in self.kind.tolist()]

    @property
    def primary_q(self) -> np.ndarray:
        return self.q[self.primary]

    def of(self, name: str):
        """(q, flags) rows of one instance, as an :class:`~app.estimators.BatchResult`."""
        from app.estimators import BatchResult
        return BatchResult(t=self.t, q=self.q[name], flags=self.flags[name])


def rows_of(samples: Iterable[Sample]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float | None]:
    """The estimator rows of a chunk of samples: times (s), kinds, values (n, 4) for the
    motion and ORI samples; and the number and last time of all samples."""
    ts, kinds, vals = [], [], []
    n_all = 0
    t_last = None
    for s in samples:
        n_all += 1
        t_last = s.time_ms
        k = KIND_OF_TAG.get(s.tag)
        if k is None:
            continue
        ts.append(s.time_ms)
        kinds.append(k)
        v = s.values
        vals.append(v if len(v) == 4 else (*v, np.nan))
    n = len(ts)
    t = np.array(ts, dtype=float).reshape(n) / 1000.0
    values = np.array(vals, dtype=float).reshape(n, 4)
    return t, np.array(kinds, dtype=np.int8).reshape(n), values, n_all, \
        (None if t_last is None else t_last / 1000.0)


class Ensemble:
    """The estimator instances and the primary (see the module doc)."""

    def __init__(self, config: dict[str, Any] | None = None):
        if config is None:
            from app.config import load_config
            config = load_config(None)
        self.instances: dict[str, Instance] = {}
        self._uids = itertools.count(1)       # every Instance this ensemble makes has its own
        for name in NAMES:
            try:
                est = estimator_class(name)(**dict(config.get(name, {})))
            except ImportError as e:  # an estimator not available: run the others
                log.warning("estimator %s unavailable: %s", name, e)
                continue
            self.instances[name] = Instance(name, name, est, builtin=True, uid=next(self._uids))
        if not self.instances:
            raise RuntimeError("no estimator available")
        p = config.get("primary")
        self.primary = p if p in self.instances else next(iter(self.instances))
        self.stopped: frozenset[str] = frozenset()
        self._version = 0
        self._publish()

    def _publish(self) -> None:
        """Replace :attr:`schema` (one attribute store: atomic for readers on other
        threads) after the instances or the primary changed."""
        self._version += 1
        self.schema = EnsembleSchema(
            MappingProxyType({n: InstanceInfo(n, i.base, i.builtin, i.uid, i.estimator)
                              for n, i in self.instances.items()}),
            self.primary, self._version)

    @classmethod
    def from_config(cls, path=None) -> "Ensemble":
        from app.config import load_config
        return cls(load_config(path))

    # ----------------------------------------------------------------- instances
    @property
    def names(self) -> list[str]:
        return list(self.instances)

    def estimator(self, name: str) -> Estimator:
        return self.instances[name].estimator

    def params_of(self, name: str):
        return self.instances[name].estimator.params

    def base_of(self, name: str) -> str:
        return self.instances[name].base

    def is_reference(self, name: str) -> bool:
        """Whether ``name`` is the phone's own estimate (``Estimator.reference``)."""
        return type(self.instances[name].estimator).reference

    def check_new(self, name: str, base: str, params: dict[str, Any] | None = None):
        """Validate a new instance; returns its parameter set. Raises EnsembleError or
        ParamError (field named), nothing changed."""
        if not isinstance(name, str) or not NAME_RE.fullmatch(name):
            raise EnsembleError("name", "1-40 lower-case letters, digits, '-' or '_', starting "
                                     "with a letter")
        if name in self.instances:
            raise EnsembleError("name", f"{name!r} is already on the bench")
        if base not in NAMES:
            raise EnsembleError("base", f"must be one of {', '.join(NAMES)}")
        if params is not None and not isinstance(params, dict):
            raise EnsembleError("params", "must be an object {param: value}")
        builtin = self.instances.get(base)
        start = builtin.estimator.params if builtin is not None else estimator_class(base).Params()
        return replace_params(start, params or {})

    def add(self, name: str, base: str, params: dict[str, Any] | None = None,
            estimator: Estimator | None = None) -> Instance:
        """A variant: estimator kind ``base`` with the builtin's current parameters changed by
        ``params``; it starts afresh (aligns on the next samples). ``estimator``: run this
        object instead (an instance of ``base``'s class or a subclass; tests, experiments)."""
        p = self.check_new(name, base, params)
        if estimator is not None and not isinstance(estimator, estimator_class(base)):
            raise EnsembleError("estimator", f"must be a {estimator_class(base).__name__}")
        inst = Instance(name, base, estimator if estimator is not None else estimator_class(base)(p),
                        builtin=False, stopped=self.stopped, uid=next(self._uids))
        self.instances[name] = inst
        self._publish()
        return inst

    def remove(self, name: str) -> None:
        inst = self.instances.get(name)
        if inst is None:
            raise EnsembleError("name", f"no instance {name!r} (known: {', '.join(self.instances)})")
        if inst.builtin:
            raise EnsembleError("name", f"{name} is built in and cannot be removed")
        del self.instances[name]
        if self.primary == name:
            self.primary = inst.base
        self._publish()

    def set_primary(self, name: str) -> None:
        if name not in self.instances:
            raise EnsembleError("primary", f"must be one of {', '.join(self.instances)}; got {name!r}")
        self.primary = name
        self._publish()

    def set_params(self, name: str, changes: dict[str, Any]) -> None:
        """Validate and apply (nothing applied on a ParamError)."""
        self.instances[name].estimator.set_params(**changes)

    def set_stopped(self, tags: frozenset[str]) -> None:
        """The stream's sensor tags that stopped while it goes on
        (:meth:`app.live.session.Session.stopped`): their last decisions are not shown."""
        if tags != self.stopped:
            self.stopped = tags
            for inst in self.instances.values():
                inst.stopped = tags

    def reset(self) -> None:
        """Every instance forgets its orientation and its bookkeeping."""
        for inst in self.instances.values():
            inst.estimator.reset()
            inst.clear()
            inst._good, inst._good_at = None, -np.inf
        self.set_stopped(frozenset())

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every instance's state (:meth:`Estimator.state_arrays`) as ``instance/attribute``
        arrays: what a recording begun into its stream keeps to re-run from it."""
        return {f"{n}/{k}": v for n, inst in self.instances.items()
                for k, v in inst.estimator.state_arrays().items()}

    def _reference(self) -> Instance | None:
        """The builtin instance holding the phone's own estimate (the reference), if any."""
        return next((i for i in self.instances.values()
                     if i.builtin and type(i.estimator).reference), None)

    @property
    def phone_q(self) -> np.ndarray | None:
        """The phone's own estimate (ORI), as the builtin reference (``phone``) validates and
        holds it;
        None before the stream's first good ORI."""
        inst = self._reference()
        est = None if inst is None else inst.estimator
        return est.q if est is not None and est.initialized else None

    # ----------------------------------------------------------------- stepping
    def step(self, samples: list[Sample]) -> Records:
        """Run every instance over the samples (time order), one batch run per instance;
        the per-row bookkeeping (counts per reason, last decision per sensor) compiled."""
        t, kind, values, n_all, t_last = rows_of(samples)
        n = t.shape[0]
        G = np.empty((n, 3))
        A = np.empty((n, 3))
        M = np.empty((n, 3))
        O = np.empty((n, 4))
        split_rows(kind, values, G, A, M, O)
        phone = self._reference()
        qs: dict[str, np.ndarray] = {}
        fls: dict[str, np.ndarray] = {}
        now = time.perf_counter()
        for name, inst in self.instances.items():
            qs[name], fls[name] = self._run(inst, now, t, G, A, M, O, kind, values)
        if phone is not None and n:     # none before the first good ORI, nor once it expired
            pq = qs[phone.name]
            phone_q = np.where(not_estimated(pq)[:, None], np.nan, pq)
        else:
            phone_q = np.full((n, 4), np.nan)
        return Records(t=t, kind=kind, values=values, q=qs, flags=fls, primary=self.primary,
                       phone_q=phone_q, n_samples=n_all, t_last=t_last)

    def _run(self, inst: Instance, now: float, t, G, A, M, O, kind,
             values) -> tuple[np.ndarray, np.ndarray]:
        """One instance over the chunk, its bookkeeping, and the guards (module doc)."""
        est = inst.estimator
        if inst._good is None or now - inst._good_at >= GOOD_EVERY_S:
            inst._good, inst._good_at = est.save_state(), now
        n = t.shape[0]
        q = np.empty((n, 4))
        f = np.empty((n, NFLAGS))
        try:
            est.run_into(t, G, A, M, O, q, f)
        except Exception:
            q, f = self._rerun(inst, t, G, A, M, O, kind, values)
        bad = tally_rows(kind, t, f, q, inst.counts, inst.last, inst.last_rejected, _IS_REJECTION)
        if bad >= 0:
            est.load_state(inst._good)
            inst.restored += 1
            log.warning("%s: estimate not finite at t = %.3f s (row %d of the chunk): last good "
                        "state restored", inst.name, t[bad], bad)
            q[bad:] = est.q
        return q, f

    def _rerun(self, inst: Instance, t, G, A, M, O, kind, values) -> tuple[np.ndarray, np.ndarray]:
        """The chunk again, row by row from the last good state; a row that raises is
        skipped (state before it restored), logged with its sample and counted."""
        est = inst.estimator
        est.load_state(inst._good)
        n = t.shape[0]
        q = np.empty((n, 4))
        f = np.empty((n, NFLAGS))
        for k in range(n):
            before = est.save_state()
            try:
                fl = est.step(t[k], G[k], A[k], M[k], O[k])
                f[k] = (fl.gyr, fl.acc, fl.acc_value, fl.acc_nis, fl.mag, fl.mag_value,
                        fl.mag_nis, float(fl.rest), fl.time)
            except Exception as e:
                est.load_state(before)
                inst.step_errors += 1
                tag = ("GYR", "ACC", "MAG", "ORI")[int(kind[k])]
                inst.last_error = f"{type(e).__name__}: {e}"
                log.exception("%s raised on the sample %.0f %s %s (skipped)", inst.name,
                              t[k] * 1000.0, tag, values[k].tolist())
                f[k] = new_flags()
            q[k] = est.q
        return q, f

    # ----------------------------------------------------------------- read-outs
    def step_errors(self) -> int:
        return sum(i.step_errors for i in self.instances.values())

    def restored(self) -> int:
        return sum(i.restored for i in self.instances.values())


__all__ = ["Ensemble", "EnsembleError", "EnsembleSchema", "Instance", "InstanceInfo", "Records", "rows_of"]
