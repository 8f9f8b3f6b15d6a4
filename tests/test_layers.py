"""The folders' floors (docs/architecture.md, "What may import what"): each floor imports
only the floors below it, so a file's folder says what it may import. Read from the
sources' import statements (function-level imports too), not from a list kept by hand."""

from __future__ import annotations

import ast
from pathlib import Path

APP = Path(__file__).resolve().parent.parent / "app"

# lowest first; a module's floor is that of its first name under app/
FLOORS = [("jitcache",), ("quaternion", "params"), ("sources", "estimators"), ("toolkit",),
          ("config", "warmup"), ("live",), ("cli", "server", "__main__")]
FLOOR = {name: i for i, names in enumerate(FLOORS) for name in names}


def _unit(module: str) -> str:
    """``app.sources.slot`` -> ``sources``; ``app.quaternion`` -> ``quaternion``."""
    return module.split(".")[1]


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] if node.module != "app" else [f"app.{a.name}" for a in node.names]
            out += [(node.lineno, n) for n in names if n.startswith("app.")]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("app.")]
    return out


def test_every_file_of_app_has_a_floor():
    units = {p.relative_to(APP).parts[0].removesuffix(".py") for p in APP.rglob("*.py")}
    assert units - {"__init__"} <= set(FLOOR), f"folders without a floor: {units - set(FLOOR)}"


def test_nothing_imports_a_floor_above_its_own():
    upward = []
    for path in sorted(APP.rglob("*.py")):
        rel = path.relative_to(APP)
        unit = rel.parts[0].removesuffix(".py")
        if unit == "__init__":
            continue
        for line, module in _imports(path):
            if FLOOR[_unit(module)] > FLOOR[unit]:
                upward.append(f"app/{rel}:{line} imports {module}")
    assert not upward, "imports upward:\n" + "\n".join(upward)


def test_a_source_knows_nothing_of_what_consumes_its_samples():
    """Wire formats in, samples out: no module of app/sources takes or drives the engine
    (the receivers and background tasks that feed it are the server's)."""
    found = []
    for path in sorted((APP / "sources").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.arg) and node.arg in ("engine", "eng"):
                found.append(f"{path.name}:{node.lineno} takes {node.arg!r}")
            elif isinstance(node, ast.Attribute) and node.attr in ("engine", "feed") \
                    and isinstance(node.value, ast.Name) and node.value.id in ("engine", "eng", "self"):
                found.append(f"{path.name}:{node.lineno} uses .{node.attr}")
    assert not found, "\n".join(found)
