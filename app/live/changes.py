"""The rule turning a PATCH body or a preset into a validated :class:`Change`.

``{"use_mag": false, "primary": "lab", "estimators": {"lab": {"acc_std": 0.3}}}``:

- a top-level parameter must be a **shared** name (:data:`app.params.SHARED_MEANINGS`:
  one physical quantity in one unit wherever it appears); it applies to every instance
  that has it. Any other parameter goes under ``estimators.<name>``: a name that only
  some estimators have means something of its own there;
- ``primary`` picks the instance drawn and plotted; ``reset: true`` forgets the
  orientation; ``estimators.<name>`` holds one instance's own changes (they win over
  top-level ones);
- a key an estimator has **renamed** is refused with a message naming the new key
  (``gyr_noise was renamed gyr_std in lab (per-sample σ, rad/s)``); presets translate it
  instead (:mod:`app.config`).

Everything is checked against copies of the current parameters; :class:`PatchError`
names the offending field (its path in the body) and nothing is applied unless every
field passes. The ensemble applies a change between two chunks (:meth:`LiveCore.apply`).

**Threads.** Validation runs wherever the request is (the event loop, viser's GUI
threads) while the filter task may add or remove a variant: it reads one
:class:`~app.live.ensemble.EnsembleSchema` (``ensemble.schema``, replaced whole by the filter
task after each change), never the live ensemble, and the :class:`Change` records which
instance (``uid``) each name meant. :func:`apply_change`, on the filter task, refuses
(PatchError "raced with another change", nothing applied) a change whose instance has
been removed or replaced since.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.config import renamed_message
from app.estimators import NAMES, estimator_class
from app.params import SHARED_MEANINGS, ParamError, fields_of, replace_params, to_dict
from app.live.ensemble import Ensemble, EnsembleError, EnsembleSchema


class PatchError(ValueError):
    """A refused change; ``loc`` is the path of the offending field in the request body."""

    def __init__(self, loc: tuple, reason: str):
        super().__init__(f"{'.'.join(map(str, loc))}: {reason}")
        self.loc = tuple(loc)
        self.reason = reason


@dataclass
class Variant:
    """An instance to add: estimator kind ``base`` with ``params`` changed."""
    name: str
    base: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class Change:
    """A validated change, applied by the live core between two chunks."""
    params: dict[str, dict[str, Any]] = field(default_factory=dict)   # instance -> changes
    primary: str | None = None
    reset: bool = False
    add: list[Variant] = field(default_factory=list)
    remove: list[str] = field(default_factory=list)
    # A preset also sets the magnetometer calibration (its [magcal] table; None: the
    # preset has none, so none is applied). Only a preset's change carries it
    # (magcal_set); the line stage that applies it listens (Engine.change_listeners).
    magcal: dict[str, Any] | None = None
    magcal_set: bool = False
    # the instances the change was validated against (name -> Instance.uid): applied only
    # if each is still on the ensemble, the same instance (not removed, not added again)
    against: dict[str, int] = field(default_factory=dict)
    # what the preset's reading said to whoever loads it (a key read as its new name, a
    # removed one left out): shown on the page and in the API's answer, not only in the log
    notes: tuple[str, ...] = ()


def _schema(ensemble: Ensemble | EnsembleSchema) -> EnsembleSchema:
    """The one immutable picture a validation reads (see the module doc)."""
    return ensemble.schema if isinstance(ensemble, Ensemble) else ensemble


def shared_names(ensemble: Ensemble | EnsembleSchema) -> list[str]:
    """The names a PATCH takes at the top level: shared quantities some instance has."""
    ensemble = _schema(ensemble)
    have = set()
    for n in ensemble.names:
        have.update(fields_of(ensemble.params_of(n)))
    return [k for k in SHARED_MEANINGS if k in have]


def common_names(ensemble: Ensemble | EnsembleSchema) -> list[str]:
    """Parameters every instance has (GET /api/params shows the primary's values)."""
    ensemble = _schema(ensemble)
    sets = [set(fields_of(ensemble.params_of(n))) for n in ensemble.names]
    return sorted(set.intersection(*sets)) if sets else []


def _top_level_refusal(ensemble: EnsembleSchema, key: str) -> str:
    owners = [n for n in ensemble.names if key in fields_of(ensemble.params_of(n))]
    renames = [m for m in (renamed_message(b, key, estimator_class(b).Params) for b in NAMES) if m]
    parts = []
    if renames:
        parts.append("; ".join(renames))
    if owners:
        f = fields_of(ensemble.params_of(owners[0]))[key].metadata
        unit = f.get("unit") or "no unit"
        parts.append(f"not a shared parameter: it is {', '.join(owners)}'s own ({unit}); "
                     f"set it under \"estimators\": {{\"{owners[0]}\": {{\"{key}\": ...}}}}")
    if not parts:
        parts.append("unknown parameter (not a parameter of any estimator; estimator-specific "
                     "ones go under \"estimators\")")
    return "; ".join(parts)


def validate_patch(ensemble: Ensemble | EnsembleSchema, body: Any) -> Change:
    """Check a PATCH body (see the module doc); the :class:`Change` or PatchError.
    Safe on any thread: it reads one schema of the ensemble."""
    if not isinstance(body, dict):
        raise PatchError(("body",), "must be a JSON object")
    ensemble = _schema(ensemble)
    names = ensemble.names
    shared = set(shared_names(ensemble))
    changes: dict[str, dict[str, Any]] = {n: {} for n in names}
    origin: dict[tuple[str, str], tuple] = {}
    ch = Change()
    for key, value in body.items():
        if key == "primary":
            if not isinstance(value, str) or value not in names:
                raise PatchError(("primary",), f"must be one of {', '.join(names)}")
            ch.primary = value
        elif key == "reset":
            if not isinstance(value, bool):
                raise PatchError(("reset",), "must be true or false")
            ch.reset = value
        elif key == "estimators":
            if not isinstance(value, dict):
                raise PatchError(("estimators",), "must be an object {estimator: {param: value}}")
            for name, sub in value.items():
                if name not in names:
                    raise PatchError(("estimators", name), f"unknown estimator (known: {', '.join(names)})")
                if not isinstance(sub, dict):
                    raise PatchError(("estimators", name), "must be an object {param: value}")
                base = ensemble.base_of(name)
                for k, v in sub.items():
                    msg = renamed_message(base, k, estimator_class(base).Params)
                    if msg is not None:
                        raise PatchError(("estimators", name, k), msg)
                    changes[name][k] = v
                    origin[(name, k)] = ("estimators", name, k)
        elif key in shared:
            for n in names:
                if key in fields_of(ensemble.params_of(n)) and (n, key) not in origin:
                    changes[n][key] = value
                    origin[(n, key)] = (key,)
        else:
            raise PatchError((key,), _top_level_refusal(ensemble, key))
    for name, c in changes.items():
        if not c:
            continue
        try:
            replace_params(ensemble.params_of(name), c)
        except ParamError as e:
            # where the client sent it (a shared key at the top: not under "estimators"),
            # with the element's index when one element is wrong ("gyr_bias[2]")
            at = origin.get((name, e.field.split("[")[0]), ("estimators", name, e.field))
            raise PatchError(at[:-1] + (e.field,), e.reason) from None
    ch.params = {n: c for n, c in changes.items() if c}
    ch.against = {n: ensemble.uid_of(n) for n in ch.params}
    if ch.primary is not None:
        ch.against[ch.primary] = ensemble.uid_of(ch.primary)
    return ch


def change_from_config(ensemble: Ensemble | EnsembleSchema, config: dict[str, Any]) -> Change:
    """A change setting every builtin to its defaults + the preset (load_config's dict)
    and the magnetometer calibration to the preset's (none if it has none); variants
    keep their parameters. Safe on any thread (one schema of the ensemble)."""
    ensemble = _schema(ensemble)
    p = config.get("primary")
    mc = config.get("magcal")
    ch = Change(primary=p if p in ensemble.instances else None, magcal=dict(mc) if mc else None,
                magcal_set=True)
    for name, info in ensemble.instances.items():
        if not info.builtin:
            continue
        params = replace_params(type(info.params)(), config.get(name, {}))
        ch.params[name] = to_dict(params)
        ch.against[name] = info.uid
    if ch.primary is not None:
        ch.against[ch.primary] = ensemble.uid_of(ch.primary)
    return ch


def _check_against(ensemble: Ensemble, ch: Change) -> None:
    """PatchError unless every instance the change names is still the one it was
    validated against (on the filter task, before anything is applied)."""
    for n, uid in ch.against.items():
        inst = ensemble.instances.get(n)
        if inst is None or inst.uid != uid:
            what = "was removed" if inst is None else "was removed and added again"
            loc = ("primary",) if n == ch.primary and n not in ch.params else ("estimators", n)
            raise PatchError(loc, f"raced with another change: {n} {what} meanwhile; "
                                  "nothing applied")
    for n in ch.params:
        if n not in ensemble.instances:
            raise PatchError(("estimators", n), f"raced with another change: no estimator {n!r} "
                                                "on the bench now; nothing applied")
    if ch.primary is not None and ch.primary not in ensemble.instances \
            and ch.primary not in {v.name for v in ch.add}:
        raise PatchError(("primary",), f"raced with another change: no estimator "
                                       f"{ch.primary!r} on the bench now; nothing applied")


def apply_change(ensemble: Ensemble, ch: Change) -> None:
    """Apply a validated change (between two chunks), on the thread that owns the ensemble
    (the filter task). Validated again against the current parameters and instances
    (another change may have come first, e.g. removed the variant it names): PatchError,
    nothing applied."""
    _check_against(ensemble, ch)
    try:
        new = {n: replace_params(ensemble.params_of(n), c) for n, c in ch.params.items()}
        for v in ch.add:
            ensemble.check_new(v.name, v.base, v.params)
        for r in ch.remove:
            if r not in ensemble.instances or ensemble.instances[r].builtin:
                raise EnsembleError("remove", f"{r!r} is not a variant on the bench")
    except ParamError as e:
        raise PatchError((e.field,), e.reason) from None
    except EnsembleError as e:
        raise PatchError((e.field,), e.reason) from None
    for n, p in new.items():
        ensemble.set_params(n, {k: getattr(p, k) for k in ch.params[n]})
    for r in ch.remove:
        ensemble.remove(r)
    for v in ch.add:
        ensemble.add(v.name, v.base, v.params)
    if ch.primary is not None:
        ensemble.set_primary(ch.primary)
    if ch.reset:
        ensemble.reset()
