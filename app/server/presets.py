"""Presets: load a TOML preset into the engine, save the current parameters as one.

Used by the GUI's Presets tab and the API (``/api/presets``). A preset name is a plain
word (letters, digits, ``-``, ``_``) stored as ``<preset_dir>/<name>.toml``; loading
also accepts the presets shipped in ``configs/``. ``default`` cannot be overwritten.
"""

from __future__ import annotations

import re
from pathlib import Path

from ..config import ConfigError, load_config
from ..params import CONFIG_DIR, dump_toml
from .engine import Change, Engine, PatchError

NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise PatchError(("name",), "a preset name is 1-64 letters, digits, '-' or '_'")
    return name


def preset_path(settings, name: str) -> Path:
    return Path(settings.preset_dir) / f"{_check_name(name)}.toml"


def list_presets(settings) -> list[str]:
    names = set()
    for d in {Path(settings.preset_dir), CONFIG_DIR}:
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.toml"))
    return sorted(names)


def load_preset(engine: Engine, name: str) -> Change:
    """A change setting every estimator to defaults + the preset ``name``."""
    path = preset_path(engine.settings, name)
    if not path.is_file():
        path = CONFIG_DIR / f"{name}.toml"
    if not path.is_file():
        raise PatchError(("name",), f"no preset named {name!r} (known: {', '.join(list_presets(engine.settings))})")
    try:
        config = load_config(path)
    except ConfigError as e:
        raise PatchError(("name",), str(e)) from None
    return engine.change_from_config(config)


def save_preset(engine: Engine, name: str) -> Path:
    """Write the current parameters of every estimator (and the primary) as a preset."""
    if name == "default":
        raise PatchError(("name",), "the default preset cannot be overwritten")
    path = preset_path(engine.settings, name)
    sections = {"primary": engine.primary}
    for n, est in engine.estimators.items():
        sections[n] = est.params_dict()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_toml(sections, header=f"orientlab preset {name!r}, saved from the dashboard"))
    return path
