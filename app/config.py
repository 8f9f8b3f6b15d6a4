"""Presets: a TOML file with one table per estimator, merged over ``configs/default.toml``.

```toml
primary = "robust"          # the estimator the dashboard shows first
[robust]
gyr_noise = 0.005
[lab]
time_update = "approx"
```

Every key is validated by the estimator's parameter set; an unknown estimator,
an unknown key or an out-of-range value is a :class:`ConfigError` naming it.

A key an estimator has renamed (``Params.renamed``, e.g. ``lab``'s ``gyr_noise``, now
``gyr_std``: the same quantity under a name that says what it is) is **translated** with
a warning naming the new key, so old presets keep loading; a preset with both the old and
the new name is refused. (The HTTP API refuses a renamed key with the same message
instead: a client should learn the new name.)
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from app.estimators import DEFAULT, NAMES, estimator_class
from app.params import DEFAULT_CONFIG, ParamError, describe, load_toml, replace_params, retired, to_dict


log = logging.getLogger("orientlab.config")


class ConfigError(ValueError):
    pass


def renamed_message(estimator: str, old: str, params_cls) -> str | None:
    """``"gyr_noise was renamed gyr_std in lab (per-sample σ, rad/s)"``, or for a parameter the
    estimator no longer has (``Params.removed``) ``"... was removed from robust (why)"``, or None."""
    gone = retired(params_cls, old)
    if gone is None:
        return None
    new, why = gone
    if new:
        return f"{old} was renamed {new} in {estimator} ({why})"
    return f"{old} was removed from {estimator} ({why})"


def translate_renamed(estimator: str, params_cls, values: dict[str, Any], source: str,
                      notes: list[str] | None = None) -> dict[str, Any]:
    """``values`` with the estimator's former parameter names replaced by the new ones and its
    removed parameters left out (a warning each: a preset saved by an older version still
    loads; each warning is also appended to ``notes``, for the user who loaded it); a
    former and a new name at once is a :class:`ConfigError`."""
    renamed = getattr(params_cls, "renamed", {})
    removed = getattr(params_cls, "removed", {})
    if not any(k in renamed or k in removed for k in values):
        return values
    out = {}
    for k, v in values.items():
        if k in removed:
            said = f"[{estimator}] {renamed_message(estimator, k, params_cls)}: left out"
            log.warning("%s: %s", source, said)
            if notes is not None:
                notes.append(said)
        elif k in renamed:
            new = renamed[k][0]
            if new in values:
                raise ConfigError(f"{source}: [{estimator}] has both {k} and {new}; "
                                  f"{renamed_message(estimator, k, params_cls)}: keep {new} only")
            said = f"[{estimator}] {renamed_message(estimator, k, params_cls)}: read as {new}"
            log.warning("%s: %s", source, said)
            if notes is not None:
                notes.append(said)
            out[new] = v
        else:
            out[k] = v
    return out


TOP_LEVEL_KEYS = ("primary",)


def merge(base: dict, over: dict) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = v
    return out


def validate_config(raw: dict[str, Any], source: str = "config") -> dict[str, Any]:
    """Check a preset; return ``{"primary": name, "<estimator>": {param: value}}``."""
    out: dict[str, Any] = {"primary": raw.get("primary", DEFAULT)}
    if out["primary"] not in NAMES:
        raise ConfigError(f"{source}: primary: unknown estimator {out['primary']!r} "
                          f"(known: {', '.join(NAMES)})")
    for key, value in raw.items():
        if key in TOP_LEVEL_KEYS:
            continue
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: unknown setting {key!r}")
        if key == "magcal":  # the magnetometer calibration (app.toolkit.magcal), not an estimator
            from app.toolkit.magcal import MagCalError, from_preset
            try:
                from_preset(value)
            except MagCalError as e:
                raise ConfigError(f"{source}: {e}") from None
            out[key] = dict(value)
            continue
        if key not in NAMES:
            raise ConfigError(f"{source}: [{key}] is not an estimator (known: {', '.join(NAMES)})")
        cls = estimator_class(key).Params
        value = translate_renamed(key, cls, value, source)
        try:
            params = replace_params(cls(), value)
        except ParamError as e:
            raise ConfigError(f"{source}: [{key}] {e}") from None
        out[key] = {k: to_dict(params)[k] for k in value}
    return out


def load_config(path: str | Path | None = None, notes: list[str] | None = None) -> dict[str, Any]:
    """``configs/default.toml`` merged with the preset at ``path`` (a file or a preset name);
    ``notes`` gets what was read as a new name or left out (:func:`translate_renamed`)."""
    raw = load_toml(DEFAULT_CONFIG) if DEFAULT_CONFIG.is_file() else {}
    src = str(DEFAULT_CONFIG)
    if path is not None:
        try:
            over = load_toml(path)
        except FileNotFoundError as e:
            raise ConfigError(str(e)) from None
        except Exception as e:  # tomllib.TOMLDecodeError and friends
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
        return config_from(over, str(path), notes)
    return validate_config(raw, src)


def config_from(over: dict[str, Any], source: str, notes: list[str] | None = None) -> dict[str, Any]:
    """``configs/default.toml`` merged with the preset table ``over`` (read from
    ``source``: a TOML file, or a recording's settings): renamed keys read as their new
    names, the whole checked (ConfigError says which value and why)."""
    raw = load_toml(DEFAULT_CONFIG) if DEFAULT_CONFIG.is_file() else {}
    over = {k: translate_renamed(k, estimator_class(k).Params, v, source, notes)
            if isinstance(v, dict) and k in NAMES else v for k, v in over.items()}
    validate_config(over, source)
    return validate_config(merge(raw, over), source)


def estimator_params(config: dict[str, Any], name: str) -> dict[str, Any]:
    return dict(config.get(name, {}))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return "(" + ", ".join(_fmt(x) for x in v) + ")"
    return "None" if v is None else str(v)


def defaults_toml() -> str:
    """``configs/default.toml`` written from the parameter definitions (the dataclasses
    are the source; a test keeps the file equal to them)."""
    from app.params import dump_toml
    lines = ["# orientlab defaults: every parameter of every estimator, SI units unless the",
             "# name says otherwise. Generated by `orientlab params --toml`; a preset given",
             "# with --config needs only the keys it changes.", "",
             f'primary = "{DEFAULT}"']
    for name in NAMES:
        cls = estimator_class(name)
        lines += ["", f"[{name}]  # {cls.title}"]
        for row in describe(cls.Params):
            if row["default"] is None:
                lines.append(f"# {row['name']} = (not set)  # {row['doc']}")
                continue
            unit = f" [{row['unit']}]" if row["unit"] else ""
            body = dump_toml({"x": {row["name"]: row["default"]}}).splitlines()[-1]
            lines.append(f"{body}  #{unit} {row['doc']}")
    return "\n".join(lines) + "\n"


def params_table() -> str:
    """The parameter table (Markdown) for the README and `orientlab params`."""
    out = []
    for name in NAMES:
        cls = estimator_class(name)
        rows = describe(cls.Params)
        sourced = any(r["default_from"] for r in rows)   # a column only where defaults say
        out += [f"### `{name}`: {cls.title}", "",
                "| parameter | default | unit | range | shown as | meaning |"
                + (" default from |" if sourced else ""),
                "|---|---|---|---|---|---|" + ("---|" if sourced else "")]
        for r in rows:
            rng = "" if r["lo"] is None and r["hi"] is None else f"{_fmt(r['lo'])} … {_fmt(r['hi'])}"
            if r["choices"]:
                rng = " / ".join(r["choices"])
            shown = r["user_unit"] if r["user_unit"] != r["unit"] else ""
            if shown and isinstance(r["default"], float):
                shown = f"{shown} ({_fmt(r['default'] * r['user_scale'])})"
            doc = r["doc"].replace("|", "\\|")     # a bare | would end the cell
            src = (" " + r["default_from"].replace("|", "\\|") + " |") if sourced else ""
            out.append(f"| `{r['name']}` | {_fmt(r['default'])} | {r['unit']} | {rng} | {shown} | {doc} |"
                       + src)
        out.append("")
    return "\n".join(out)
