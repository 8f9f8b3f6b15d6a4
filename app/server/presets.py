"""Presets: load a TOML preset into the engine, save the current parameters as one.

Used by the GUI's Presets tab and the API (``/api/presets``).

- **Where.** Presets saved from the dashboard go to the user's folder
  (``Settings.preset_dir``: ``--presets-dir``, ``$ORIENTLAB_PRESETS``, else
  ``~/.local/share/orientlab/presets``), never into the source tree. The presets shipped
  in ``configs/`` are read-only: a saved preset cannot take a shipped name.
- **Names** are checked with ``re.fullmatch`` (1-64 letters, digits, ``-``, ``_``; no
  trailing newline, no path): ``<preset_dir>/<name>.toml``. At most
  ``Settings.max_presets`` are saved (then saving a new name is refused).
- **One save path** (:func:`write_preset`) for every preset: the dashboard's "save",
  an uploaded file kept, a calibration's ``save_as`` (:meth:`app.server.toolkit.Toolkit.save_preset`).
- **Writes are atomic**: a temporary file in the same folder, then ``os.replace``; a
  folder that refuses the write (read-only, full) is :class:`PresetWriteError` (HTTP
  507 with the reason), nothing left behind.
- **Loading** by name (the user's folder first, then the shipped ones), from a **path**
  (a file written by ``orientlab calibrate``, anywhere on this PC), or from the **text**
  of an uploaded file (at most :data:`MAX_PRESET_BYTES`); each sets every estimator to
  its defaults plus the preset, after the same validation as ``--config``, and the
  magnetometer calibration to the preset's ``[magcal]`` (none when it has none: a preset
  is the whole tuning; :class:`app.toolkit.magcal.MagCalService` applies it). Saving writes the
  magnetometer calibration in force too.
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import replace
from pathlib import Path

from app.config import ConfigError, config_from, load_config
from app.params import CONFIG_DIR, dump_toml
from app.live import Change, PatchError
from app.server.engine import Engine

try:
    import tomllib
except ImportError:  # Python 3.10 (pyproject: requires-python >= 3.10; tomli is a dependency there)
    import tomli as tomllib

NAME_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
MAX_PRESET_BYTES = 64 * 1024


def _check_name(name) -> str:
    if not isinstance(name, str) or NAME_RE.fullmatch(name) is None:
        raise PatchError(("name",), "a preset name is 1-64 letters, digits, '-' or '_'")
    return name


def preset_path(settings, name: str) -> Path:
    return Path(settings.preset_dir) / f"{_check_name(name)}.toml"


def shipped_names() -> set[str]:
    return {p.stem for p in CONFIG_DIR.glob("*.toml")} if CONFIG_DIR.is_dir() else set()


def _saved(settings) -> list[Path]:
    d = Path(settings.preset_dir)
    return [p for p in d.glob("*.toml") if NAME_RE.fullmatch(p.stem)] if d.is_dir() else []


def list_presets(settings) -> list[str]:
    return sorted(shipped_names() | {p.stem for p in _saved(settings)})


def load_preset(engine: Engine, name: str) -> Change:
    """A change setting every estimator to defaults + the preset ``name``."""
    path = preset_path(engine.settings, name)
    if not path.is_file():
        path = CONFIG_DIR / f"{name}.toml"
    if not path.is_file():
        raise PatchError(("name",), f"no preset named {name!r} "
                                    f"(known: {', '.join(list_presets(engine.settings))})")
    return _change_from_path(engine, path, ("name",))


def load_preset_path(engine: Engine, path) -> Change:
    """A change from the preset file at ``path`` (e.g. written by ``orientlab calibrate``)."""
    if not isinstance(path, str) or not path.strip() or len(path) > 4096:
        raise PatchError(("path",), "the path of a preset file (.toml)")
    p = Path(path.strip()).expanduser()
    if not p.is_file():
        raise PatchError(("path",), f"no such file: {str(p)[:200]}")
    if p.stat().st_size > MAX_PRESET_BYTES:
        raise PatchError(("path",), f"larger than {MAX_PRESET_BYTES // 1024} KB: not a preset")
    return _change_from_path(engine, p, ("path",))


def _change_from_path(engine: Engine, path: Path, loc: tuple) -> Change:
    notes: list[str] = []
    try:
        config = load_config(path, notes)
    except ConfigError as e:
        raise PatchError(loc, str(e)[:300]) from None
    return replace(engine.core.change_from_config(config), notes=tuple(notes))


def config_from_text(text: str | bytes, source: str = "upload",
                     notes: list[str] | None = None) -> dict:
    """``configs/default.toml`` merged with a preset given as text; ConfigError if bad."""
    if isinstance(text, bytes):
        if len(text) > MAX_PRESET_BYTES:
            raise ConfigError(f"{source}: larger than {MAX_PRESET_BYTES // 1024} KB: not a preset")
        text = text.decode("utf-8", errors="replace")
    if len(text) > MAX_PRESET_BYTES:
        raise ConfigError(f"{source}: larger than {MAX_PRESET_BYTES // 1024} KB: not a preset")
    try:
        over = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: not valid TOML: {str(e)[:200]}") from None
    return config_from(over, source, notes)   # former names read as the new, as --config does


def load_preset_text(engine: Engine, text: str | bytes, source: str = "upload") -> Change:
    """A change from a preset's text (an uploaded file)."""
    notes: list[str] = []
    try:
        config = config_from_text(text, source, notes)
    except ConfigError as e:
        raise PatchError(("file",), str(e)[:300]) from None
    return replace(engine.core.change_from_config(config), notes=tuple(notes))


class PresetWriteError(PatchError):
    """The preset folder refused the write (read-only, full, not a folder...): nothing
    was written (an HTTP 507 with ``reason``, never a 500)."""

    status = 507


def _check_writable(settings, name: str) -> Path:
    _check_name(name)
    if name in shipped_names():
        raise PatchError(("name",), f"{name!r} is a shipped preset (read-only): "
                                    "save under another name")
    path = preset_path(settings, name)
    cap = int(getattr(settings, "max_presets", 200))
    if not path.exists() and len(_saved(settings)) >= cap:
        raise PatchError(("name",), f"already {cap} saved presets: delete some in "
                                    f"{settings.preset_dir} first")
    return path


def check_save(settings, name: str) -> Path:
    """Would :func:`write_preset` take ``name``? Its path, or the PatchError it would
    raise (the name rules, a shipped name, the cap); e.g. before a calibration is
    applied with ``save_as``, so a refused name applies nothing."""
    return _check_writable(settings, name)


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_preset(settings, name: str, text: str | bytes) -> Path:
    """**The** way a preset is saved (the dashboard's "save", an upload kept, a
    calibration's ``save_as``): the name is checked (the name rules, no shipped name),
    the cap (``Settings.max_presets``) applies to a new name, the file is written
    atomically (a temporary file, then ``os.replace``: a reader never sees half a
    preset, a failed write leaves the old file and no temporary). PatchError for a
    refused name; :class:`PresetWriteError` when the folder refuses the write."""
    path = _check_writable(settings, name)
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    try:
        _write_atomic(path, text)
    except OSError as e:
        why = e.strerror or type(e).__name__
        raise PresetWriteError(("name",), f"cannot write the preset {name!r} in "
                                          f"{str(settings.preset_dir)[:200]}: {why}") from None
    return path


def save_preset(engine: Engine, name: str, header: str | None = None) -> Path:
    """Write the current parameters of every estimator (and the primary) as a preset in
    the user's folder (:func:`write_preset`). The magnetometer calibration in force
    comes from ``engine.preset_parts``. ``header``: the file's comment (a calibration
    puts its report there)."""
    _check_writable(engine.settings, name)      # refused before anything is gathered
    sections = engine.core.preset_sections()
    for part in engine.preset_parts:      # e.g. the magnetometer calibration in force
        sections.update(part())
    if header is None:
        header = f"orientlab preset {name!r}, saved from the dashboard"
    return write_preset(engine.settings, name, dump_toml(sections, header=header))


def save_preset_text(settings, name: str, text: str | bytes) -> Path:
    """Keep an uploaded preset (already validated) in the user's folder under ``name``."""
    return write_preset(settings, name, text)
