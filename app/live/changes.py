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
field passes. The bench applies a change between two chunks (:meth:`LiveCore.apply`).

**Threads.** Validation runs wherever the request is (the event loop, viser's GUI
threads) while the filter task may add or remove a variant: it reads one
:class:`~app.live.bench.BenchSchema` (``bench.schema``, replaced whole by the filter
task after each change), never the live bench, and the :class:`Change` records which
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
from app.live.bench import Bench, BenchError, BenchSchema


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
    # if each is still on the bench, the same instance (not removed, not added again)
    against: dict[str, int] = field(default_factory=dict)


def _schema(bench: Bench | BenchSchema) -> BenchSchema:
    """The one immutable picture a validation reads (see the module doc)."""
    return bench.schema if isinstance(bench, Bench) else bench


def shared_names(bench: Bench | BenchSchema) -> list[str]:
    """The names a PATCH takes at the top level: shared quantities some instance has."""
    bench = _schema(bench)
    have = set()
    for n in bench.names:
        have.update(fields_of(bench.params_of(n)))
    return [k for k in SHARED_MEANINGS if k in have]


def common_names(bench: Bench | BenchSchema) -> list[str]:
    """Parameters every instance has (GET /api/params shows the primary's values)."""
    bench = _schema(bench)
    sets = [set(fields_of(bench.params_of(n))) for n in bench.names]
    return sorted(set.intersection(*sets)) if sets else []


def _top_level_refusal(bench: BenchSchema, key: str) -> str:
    owners = [n for n in bench.names if key in fields_of(bench.params_of(n))]
    renames = [m for m in (renamed_message(b, key, estimator_class(b).Params) for b in NAMES) if m]
    parts = []
    if renames:
        parts.append("; ".join(renames))
    if owners:
        f = fields_of(bench.params_of(owners[0]))[key].metadata
        unit = f.get("unit") or "no unit"
        parts.append(f"not a shared parameter: it is {', '.join(owners)}'s own ({unit}); "
                     f"set it under \"estimators\": {{\"{owners[0]}\": {{\"{key}\": ...}}}}")
    if not parts:
        parts.append("unknown parameter (not a parameter of any estimator; estimator-specific "
                     "ones go under \"estimators\")")
    return "; ".join(parts)


def validate_patch(bench: Bench | BenchSchema, body: Any) -> Change:
    """Check a PATCH body (see the module doc); the :class:`Change` or PatchError.
    Safe on any thread: it reads one schema of the bench."""
    if not isinstance(body, dict):
        raise PatchError(("body",), "must be a JSON object")
    bench = _schema(bench)
    names = bench.names
    shared = set(shared_names(bench))
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
                base = bench.base_of(name)
                for k, v in sub.items():
                    msg = renamed_message(base, k, estimator_class(base).Params)
                    if msg is not None:
                        raise PatchError(("estimators", name, k), msg)
                    changes[name][k] = v
                    origin[(name, k)] = ("estimators", name, k)
        elif key in shared:
            for n in names:
                if key in fields_of(bench.params_of(n)) and (n, key) not in origin:
                    changes[n][key] = value
                    origin[(n, key)] = (key,)
        else:
            raise PatchError((key,), _top_level_refusal(bench, key))
    for name, c in changes.items():
        if not c:
            continue
        try:
            replace_params(bench.params_of(name), c)
        except ParamError as e:
            raise PatchError(origin.get((name, e.field), ("estimators", name, e.field)),
                             e.reason) from None
    ch.params = {n: c for n, c in changes.items() if c}
    ch.against = {n: bench.uid_of(n) for n in ch.params}
    if ch.primary is not None:
        ch.against[ch.primary] = bench.uid_of(ch.primary)
    return ch


def change_from_config(bench: Bench | BenchSchema, config: dict[str, Any]) -> Change:
    """A change setting every builtin to its defaults + the preset (load_config's dict)
    and the magnetometer calibration to the preset's (none if it has none); variants
    keep their parameters. Safe on any thread (one schema of the bench)."""
    bench = _schema(bench)
    p = config.get("primary")
    mc = config.get("magcal")
    ch = Change(primary=p if p in bench.instances else None, magcal=dict(mc) if mc else None,
                magcal_set=True)
    for name, info in bench.instances.items():
        if not info.builtin:
            continue
        params = replace_params(type(info.params)(), config.get(name, {}))
        ch.params[name] = to_dict(params)
        ch.against[name] = info.uid
    if ch.primary is not None:
        ch.against[ch.primary] = bench.uid_of(ch.primary)
    return ch


def _check_against(bench: Bench, ch: Change) -> None:
    """PatchError unless every instance the change names is still the one it was
    validated against (on the filter task, before anything is applied)."""
    for n, uid in ch.against.items():
        inst = bench.instances.get(n)
        if inst is None or inst.uid != uid:
            what = "was removed" if inst is None else "was removed and added again"
            loc = ("primary",) if n == ch.primary and n not in ch.params else ("estimators", n)
            raise PatchError(loc, f"raced with another change: {n} {what} meanwhile; "
                                  "nothing applied")
    for n in ch.params:
        if n not in bench.instances:
            raise PatchError(("estimators", n), f"raced with another change: no estimator {n!r} "
                                                "on the bench now; nothing applied")
    if ch.primary is not None and ch.primary not in bench.instances \
            and ch.primary not in {v.name for v in ch.add}:
        raise PatchError(("primary",), f"raced with another change: no estimator "
                                       f"{ch.primary!r} on the bench now; nothing applied")


def apply_change(bench: Bench, ch: Change) -> None:
    """Apply a validated change (between two chunks), on the thread that owns the bench
    (the filter task). Validated again against the current parameters and instances
    (another change may have come first, e.g. removed the variant it names): PatchError,
    nothing applied."""
    _check_against(bench, ch)
    try:
        new = {n: replace_params(bench.params_of(n), c) for n, c in ch.params.items()}
        for v in ch.add:
            bench.check_new(v.name, v.base, v.params)
        for r in ch.remove:
            if r not in bench.instances or bench.instances[r].builtin:
                raise BenchError("remove", f"{r!r} is not a variant on the bench")
    except ParamError as e:
        raise PatchError((e.field,), e.reason) from None
    except BenchError as e:
        raise PatchError((e.field,), e.reason) from None
    for n, p in new.items():
        bench.set_params(n, {k: getattr(p, k) for k in ch.params[n]})
    for r in ch.remove:
        bench.remove(r)
    for v in ch.add:
        bench.add(v.name, v.base, v.params)
    if ch.primary is not None:
        bench.set_primary(ch.primary)
    if ch.reset:
        bench.reset()
