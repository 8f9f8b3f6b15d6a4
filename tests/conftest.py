"""Shared fixtures. ``shared_dir``: the ``../shared`` folder beside the repository
(real logs and data sets, never copied into the repo), or the test is skipped."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} not present (real data lives beside the repository)")
    return SHARED


# The real Sensor Fusion app logs (shared/data/sensorfusion-app/SOURCES.md)
REAL_LOGS = (
    "alekodu_activityrecognition/sensorLog_20221024T182616_standstill.txt",
    "alekodu_activityrecognition/sensorLog_20221024T182635_walking_hand.txt",
    "alekodu_activityrecognition/sensorLog_20221024T182709_walking_pocket.txt",
    "alekodu_activityrecognition/sensorLog_20221024T182741_running_hand.txt",
    "alekodu_activityrecognition/sensorLog_20221024T182818_running_pocket.txt",
    "alekodu_activityrecognition/sensorLog_20221024T183036_walking_pocket_long_time.txt",
    "BaiLiping_WASP_IMU/sensorLog.txt",
    "BaiLiping_WASP_IMU/data1.txt",
    "BaiLiping_WASP_IMU/run1.txt",
)
# those with gyroscope and magnetometer too (the BaiLiping logs hold only ACC)
REAL_LOGS_9DOF = tuple(p for p in REAL_LOGS if p.startswith("alekodu_"))


@pytest.fixture(params=REAL_LOGS, ids=lambda p: Path(p).stem)
def real_log(request, shared_dir) -> Path:
    """Each real app log in turn (skipped when absent)."""
    return _app_log(shared_dir, request.param)


def _app_log(shared_dir: Path, name: str) -> Path:
    path = shared_dir / "data" / "sensorfusion-app" / name
    if not path.is_file():
        pytest.skip(f"{path} not present")
    return path


@pytest.fixture(params=REAL_LOGS_9DOF, ids=lambda p: Path(p).stem)
def real_log_9dof(request, shared_dir) -> Path:
    """Each real app log with accelerometer, gyroscope and magnetometer."""
    return _app_log(shared_dir, request.param)


# Tests live in folders that mirror the package (sources, estimators, live, toolkit,
# server); the shared helpers (harness.py) stay here, importable from every folder.
import sys as _sys

_HERE = Path(__file__).resolve().parent
_sys.path[:0] = [str(_HERE), str(_HERE / "sources")]   # + the apps' data converters


@pytest.fixture(autouse=True)
def _fresh_log_rate_limit(request):
    """The log's rate limit (app.server.limits) is one per process and keyed by the line's
    format: a test that reads the log (``caplog``) must not find its lines suppressed because
    a test before it, in the same worker, said the same thing five times in 10 s."""
    if "caplog" in request.fixturenames:
        from app.server.limits import reset_log_limits
        reset_log_limits()
    yield
