"""Typed, validated parameter sets: SI units inside, the unit in every non-SI name.

Every estimator has one frozen dataclass of parameters. Each field carries its
metadata (unit, valid range, the unit shown to users and a sentence of help), so
validation, the TOML presets, the HTTP API and the GUI all read one definition.
Changing parameters always goes through :func:`replace_params`, which checks every
changed field first and applies nothing if any is refused.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib


class ParamError(ValueError):
    """A refused parameter change: ``field`` names the parameter, ``reason`` says why."""

    def __init__(self, field_name: str, reason: str):
        super().__init__(f"{field_name}: {reason}")
        self.field = field_name
        self.reason = reason

    def __reduce__(self):
        # rebuilt from its two arguments, not from the message: it crosses a process pool
        # (the benchmarks run trials in worker processes) with its text intact
        return type(self), (self.field, self.reason)


def param(default, *, unit: str = "", lo: float | None = None, hi: float | None = None,
      doc: str = "", user_unit: str | None = None, user_scale: float = 1.0,
      choices: tuple | None = None, log: bool = False, tunable: bool = True,
      length: int | None = None, optional: bool = False, integer: bool | None = None,
      rejects: bool = False):
    """A parameter field. ``user_unit``/``user_scale`` give the unit shown to users:
    ``user_value = value * user_scale`` (for example rad/s shown as deg/s).
    ``log`` marks a quantity tuned over decades (noise levels). ``rejects`` marks a
    rejection or de-weighting of a sensor's data (a gate, a band, a noise added for a
    deviating field) that its off value switches off: 0, or None for an optional one (the
    no-rejection variant, :func:`app.toolkit.variants.no_rejection_changes`, turns every
    such parameter off)."""
    if rejects and not (optional or "0: off" in doc):
        raise ValueError(f"a rejecting parameter needs an off value (0: off, or optional): {doc!r}")
    meta = dict(unit=unit, lo=lo, hi=hi, doc=doc, user_unit=user_unit or unit,
                user_scale=user_scale, choices=choices, log=log, tunable=tunable,
                length=length, optional=optional, rejects=rejects,
                integer=isinstance(default, int) and not isinstance(default, bool)
                if integer is None else integer)
    if isinstance(default, list):
        default = tuple(default)
    if isinstance(default, tuple):
        return field(default_factory=lambda d=tuple(default): d, metadata=meta)
    return field(default=default, metadata=meta)


def gyr_scale_param():
    """``gyr_scale``, the gyroscope's scale-factor calibration (``orientlab gyro-scale``): one
    definition for every estimator that applies it."""
    return param((0.0, 0.0, 0.0), lo=-0.1, hi=0.1, tunable=False,
                 doc="gyroscope scale-factor error per sensor axis (calibration: orientlab gyro-scale): "
                     "the gyroscope reads (1 + s) × the turn, so each axis, its bias removed, is "
                     "divided by 1 + s")


DEG = 180.0 / math.pi
# m/s²: the specific force a phone at rest reads, up (acc ≈ Q(q)ᵀ [0, 0, GRAVITY]); the
# one value of g in orientlab (an app's own unit "g" is converted where it is read)
GRAVITY = 9.81


def short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters: an error message never echoes a big input."""
    r = repr(value) if not isinstance(value, (list, tuple, dict)) or len(value) <= 64 \
        else f"<{type(value).__name__} of {len(value)} items>"
    return r if len(r) <= limit else r[:limit - 3] + "..."


def _check_number(name: str, value: Any, meta: dict) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamError(name, f"must be a number, got {short(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise ParamError(name, f"must be finite, got {short(value)}")
    lo, hi = meta.get("lo"), meta.get("hi")
    unit = meta.get("unit") or ""
    if lo is not None and v < lo:
        raise ParamError(name, f"{v:g} is below the minimum {lo:g} {unit}".rstrip())
    if hi is not None and v > hi:
        raise ParamError(name, f"{v:g} is above the maximum {hi:g} {unit}".rstrip())
    return v


def coerce(name: str, value: Any, current: Any, meta: dict) -> Any:
    """Check one value against the field's type and range; return it in canonical form."""
    choices = meta.get("choices")
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ParamError(name, f"must be true or false, got {short(value)}")
        return value
    if choices is not None:
        if not isinstance(value, (str, int, float)) or value not in choices:
            raise ParamError(name, f"must be one of {', '.join(map(str, choices))}; got {short(value)}")
        return value
    length = meta.get("length")
    if isinstance(current, tuple) or length:
        if value is None and meta.get("optional"):
            return None
        n = length or len(current)
        if isinstance(value, (list, tuple)) and value and isinstance(value[0], (list, tuple)):
            # a matrix given row by row: every row a list of the same length
            if not all(isinstance(row, (list, tuple)) and len(row) == len(value[0]) for row in value):
                raise ParamError(name, f"a matrix must have rows of equal length (a list of {n} "
                                       f"numbers, or rows of numbers), got {short(value)}")
            value = [x for row in value for x in row]
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise ParamError(name, f"must be a list of {n} numbers, got {short(value)}")
        return tuple(_check_number(f"{name}[{i}]", v, meta) for i, v in enumerate(value))
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ParamError(name, f"must be text, got {short(value)}")
        return value
    if isinstance(current, int) and not isinstance(current, bool) and meta.get("integer"):
        v = _check_number(name, value, meta)
        if v != int(v):
            raise ParamError(name, f"must be a whole number, got {short(value)}")
        return int(v)
    if current is None:
        if value is None:
            return None
        return _check_number(name, value, meta)
    return _check_number(name, value, meta)


def fields_of(params_or_cls) -> dict[str, dataclasses.Field]:
    return {f.name: f for f in dataclasses.fields(params_or_cls)}


def retired(params_cls, name: str) -> tuple[str | None, str] | None:
    """A name the class no longer has: ``(new name, why)`` for a renamed parameter
    (``Params.renamed``), ``(None, why)`` for a removed one (``Params.removed``), else None."""
    new = getattr(params_cls, "renamed", {}).get(name)
    if new is not None:
        return new[0], new[1]
    why = getattr(params_cls, "removed", {}).get(name)
    return None if why is None else (None, why)


def replace_params(params, changes: dict[str, Any]):
    """A new parameter set with ``changes`` applied, or ParamError naming the first
    refused field. Unknown keys are refused; nothing is applied unless all pass."""
    fmap = fields_of(params)
    clean = {}
    for name, value in changes.items():
        if name not in fmap:
            gone = retired(type(params), name)
            if gone is not None:
                raise ParamError(name, f"was renamed {gone[0]} ({gone[1]})" if gone[0]
                                 else f"was removed ({gone[1]})")
            raise ParamError(name, f"unknown parameter for {type(params).__name__} "
                                   f"(known: {', '.join(sorted(fmap))})")
        clean[name] = coerce(name, value, getattr(params, name), fmap[name].metadata)
    new = dataclasses.replace(params, **clean)
    check = getattr(new, "check", None)
    if check is not None:
        check()  # cross-field rules, raise ParamError
    return new


def to_dict(params) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(params):
        v = getattr(params, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def describe(params_cls) -> list[dict[str, Any]]:
    """The parameter table: name, default, unit, range, user unit, help, and where the default
    comes from (``default_from``: a class's optional name → source map; "" where none)."""
    rows = []
    defaults = params_cls()
    sources = getattr(params_cls, "default_from", {})
    for f in dataclasses.fields(params_cls):
        m = f.metadata
        v = getattr(defaults, f.name)
        rows.append(dict(name=f.name, default=list(v) if isinstance(v, tuple) else v,
                         unit=m.get("unit", ""), lo=m.get("lo"), hi=m.get("hi"),
                         user_unit=m.get("user_unit", ""), user_scale=m.get("user_scale", 1.0),
                         choices=m.get("choices"), log=m.get("log", False), doc=m.get("doc", ""),
                         tunable=m.get("tunable", True), integer=m.get("integer", False),
                         default_from=sources.get(f.name, "")))
    return rows


# ----------------------------------------------------------------- presets (TOML)

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
DEFAULT_CONFIG = CONFIG_DIR / "default.toml"


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        # a bare preset name: look in configs/
        alt = CONFIG_DIR / (str(path) if str(path).endswith(".toml") else f"{path}.toml")
        if alt.is_file():
            path = alt
        else:
            raise FileNotFoundError(f"no such config file: {path}")
    with open(path, "rb") as fh:
        return tomllib.load(fh)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def dump_toml(sections: dict[str, dict[str, Any]], header: str = "") -> str:
    """Write nested ``{section: {key: value}}`` as TOML (None values are left out)."""
    lines = [f"# {ln}" if ln else "#" for ln in header.splitlines()] if header else []
    top = {k: v for k, v in sections.items() if not isinstance(v, dict)}
    for k, v in top.items():
        if v is not None:
            lines.append(f"{k} = {_toml_value(v)}")
    for name, sec in sections.items():
        if not isinstance(sec, dict):
            continue
        lines.append("")
        lines.append(f"[{name}]")
        for k, v in sec.items():
            if v is None:
                continue
            if isinstance(v, (list, tuple)) and v and isinstance(v[0], (list, tuple)):
                inner = ",\n    ".join(_toml_value(r) for r in v)
                lines.append(f"{k} = [\n    {inner},\n]")
            else:
                lines.append(f"{k} = {_toml_value(v)}")
    return "\n".join(lines) + "\n"


# One meaning per name: a parameter name that more than one estimator has is one physical
# quantity in one unit everywhere, declared here (tests/test_params.py checks every shared
# name against this table and the units of its definitions). Only these names are taken
# at the top level of PATCH /api/params (they set every estimator that has them).
# Naming rule: ``*_noise`` is a noise density, ``*_std`` a per-sample σ. A process noise
# density is per √s (rad/√s); a measurement's is times √s (rad·√s: R = σ²/Δt).
SHARED_MEANINGS: dict[str, str] = {
    "use_gyr": "use the gyroscope (switch)",
    "use_acc": "use the accelerometer (switch)",
    "use_mag": "use the magnetometer (switch)",
    "max_gap": "longest time step integrated (s); a longer one is a gap",
    "gyr_hold": "how long the last gyroscope sample stands in for rows without one (s)",
    "gyr_bias": "gyroscope bias from calibration, sensor frame (rad/s)",
    "gyr_scale": "gyroscope scale-factor error from calibration, per sensor axis: it reads (1 + s) × the turn",
    "acc_band_rel": "half-width of the accepted |acc| band, relative to |g| (0: no band)",
}


@dataclass(frozen=True)
class CommonParams:
    """Parameters every estimator has: a switch per sensor (lab manual, exercise 9)
    and the time-step limits that keep bad timestamps from doing harm."""
    use_gyr: bool = param(True, doc="use the gyroscope (off: lab and robust keep the attitude as a "
                                        "random walk, complementary takes the compass as it is; phone: "
                                        "the phone's own estimate, not switched)")
    use_acc: bool = param(True, doc="use the accelerometer")
    use_mag: bool = param(True, doc="use the magnetometer")
    max_gap: float = param(1.0, unit="s", lo=0.01, hi=60.0,
                           doc="a time step longer than this is a gap: no integration across it")
    gyr_hold: float = param(0.1, unit="s", lo=0.0, hi=5.0,
                            doc="how long the last gyroscope sample is held for rows without one")

    def check(self) -> None:
        """Cross-field rules; subclasses extend it."""
