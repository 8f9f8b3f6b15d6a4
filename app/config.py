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
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .estimators import DEFAULT, NAMES, estimator_class
from .params import DEFAULT_CONFIG, ParamError, load_toml, replace_params, to_dict


class ConfigError(ValueError):
    pass


TOP_LEVEL_KEYS = ("primary",)


def _merge(base: dict, over: dict) -> dict:
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
        if key not in NAMES:
            raise ConfigError(f"{source}: [{key}] is not an estimator (known: {', '.join(NAMES)})")
        try:
            params = replace_params(estimator_class(key).Params(), value)
        except ParamError as e:
            raise ConfigError(f"{source}: [{key}] {e}") from None
        out[key] = {k: to_dict(params)[k] for k in value}
    return out


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    """``configs/default.toml`` merged with the preset at ``path`` (a file or a preset name)."""
    raw = load_toml(DEFAULT_CONFIG) if DEFAULT_CONFIG.is_file() else {}
    src = str(DEFAULT_CONFIG)
    if path is not None:
        try:
            over = load_toml(path)
        except FileNotFoundError as e:
            raise ConfigError(str(e)) from None
        except Exception as e:  # tomllib.TOMLDecodeError and friends
            raise ConfigError(f"{path}: not valid TOML: {e}") from None
        validate_config(over, str(path))
        raw = _merge(raw, over)
        src = str(path)
    return validate_config(raw, src)


def estimator_params(config: dict[str, Any], name: str) -> dict[str, Any]:
    return dict(config.get(name, {}))
