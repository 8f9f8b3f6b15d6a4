"""app.jitcache: a numba cache older than any compiled source is dropped (numba itself
checks a function against its own file only, so a change to base.py would leave the
old code inlined in robust.py's cache)."""

from __future__ import annotations

from app.jitcache import STAMP, cache_files, compiled_sources, refresh


def _tree(tmp_path):
    (tmp_path / "estimators" / "__pycache__").mkdir(parents=True)
    (tmp_path / "__pycache__").mkdir()
    (tmp_path / "jitcache.py").write_text("compiled = 1\n")
    (tmp_path / "quaternion.py").write_text("def q(): pass\n")
    (tmp_path / "estimators" / "base.py").write_text("def align(): pass\n")
    (tmp_path / "estimators" / "robust.py").write_text("def run(): pass\n")
    return tmp_path


def _cache(root):
    for name in ("estimators/__pycache__/robust.run-1.py311.nbi",
                 "estimators/__pycache__/robust.run-1.py311.1.nbc",
                 "__pycache__/quaternion.q-1.py311.nbi"):
        (root / name).write_bytes(b"x")
    (root / "estimators" / "__pycache__" / "robust.cpython-311.pyc").write_bytes(b"x")


def test_a_changed_source_drops_every_compiled_cache_entry_and_nothing_else(tmp_path):
    root = _tree(tmp_path)
    assert [p.name for p in compiled_sources(root)] == ["jitcache.py", "quaternion.py", "base.py", "robust.py"]
    assert not refresh(root)                   # a fresh install: no cache, nothing dropped
    assert (root / "estimators" / "__pycache__" / STAMP).is_file()
    (root / "estimators" / "__pycache__" / STAMP).unlink()
    _cache(root)
    assert refresh(root)                       # no stamp yet: whatever is cached is unknown
    assert cache_files(root) == []
    assert (root / "estimators" / "__pycache__" / STAMP).is_file()
    _cache(root)                               # numba compiles and caches again
    assert not refresh(root)                   # nothing changed: the cache stays
    assert len(cache_files(root)) == 3
    (root / "estimators" / "base.py").write_text("def align(): return 1\n")
    assert refresh(root)                       # base.py alone changed: robust's entry goes too
    assert cache_files(root) == []
    assert (root / "estimators" / "__pycache__" / "robust.cpython-311.pyc").is_file()
    assert not refresh(root)
    _cache(root)
    (root / "jitcache.py").write_text("compiled = 2\n")
    assert refresh(root)                       # how they compile changed: every entry goes
    assert cache_files(root) == []
