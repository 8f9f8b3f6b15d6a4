"""numba's on-disk cache, kept true to the sources.

numba checks a cached function against its *own* file only. A compiled function that
calls one from another file (``robust_run`` calls ``base.align_step``,
``kalman.correct``, ``quaternion.rotate``...) carries that code inlined, so after a
change to ``base.py`` alone the cache of ``robust.py`` would still load, with the old
``align_step`` in it: a ``git pull`` would run old filter code without a word.

:func:`ensure_fresh` keeps a digest of every compiled source beside the cache and, when
it differs, drops every cache entry of those sources: the next start compiles them
afresh (``orientlab compile`` says so and does it ahead of time). It runs once per
process, before anything compiled is called (``app.quaternion`` calls it on import).
"""

from __future__ import annotations

from functools import cache
from hashlib import sha256
from pathlib import Path

ROOT = Path(__file__).resolve().parent
STAMP = "numba-sources.sha256"


def compiled_sources(root: Path = ROOT) -> list[Path]:
    """Every source file with numba-compiled functions (the estimators' packages too:
    ``estimators/robust/``)."""
    return [root / "quaternion.py", *sorted((root / "estimators").rglob("*.py"))]


def sources_digest(root: Path = ROOT) -> str:
    h = sha256()
    for p in compiled_sources(root):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def cache_files(root: Path = ROOT) -> list[Path]:
    """numba's cache entries (index and data) of the compiled sources."""
    out = []
    for src in compiled_sources(root):
        out += [f for f in (src.parent / "__pycache__").glob(src.stem + ".*")
                if f.suffix in (".nbi", ".nbc")]
    return out


@cache
def ensure_fresh() -> bool:
    """:func:`refresh` for this install, once per process."""
    return refresh(ROOT)


def refresh(root: Path) -> bool:
    """Drop the compiled sources' cache entries under ``root`` when any of those
    sources changed since they were cached. True when there were entries to drop (a
    fresh install has none: nothing to say). A read-only install is left as it is."""
    stamp = root / "estimators" / "__pycache__" / STAMP
    digest = sources_digest(root)
    try:
        if stamp.read_text().strip() == digest:
            return False
    except OSError:
        pass
    stale = cache_files(root)
    try:
        for f in stale:
            f.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_suffix(".tmp")
        tmp.write_text(digest + "\n")
        tmp.replace(stamp)
    except OSError:
        return False
    return bool(stale)
