"""``orientlab calibrate`` writes no preset from a recording of a phone that moved unless
``--force`` (issue 21, item 1): the real command on a real log."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LOGS = "data/sensorfusion-app/alekodu_activityrecognition/"


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)


def test_a_moving_phone_needs_force(tmp_path, shared_dir):
    moving = shared_dir / LOGS / "sensorLog_20221024T182635_walking_hand.txt"
    out = tmp_path / "moved.toml"
    p = _cli("calibrate", moving, "--out", out)
    assert p.returncode == 1, (p.returncode, p.stderr)
    assert "WARNING: this recording does not look stationary" in p.stdout     # the report
    assert f"not writing {out}" in p.stderr and "the phone moved" in p.stderr
    assert "--force" in p.stderr
    assert not out.exists()
    p = _cli("calibrate", moving, "--out", out, "--force")
    assert p.returncode == 0, p.stderr
    assert "anyway (--force)" in p.stderr and out.is_file()
    assert "[lab]" in out.read_text(encoding="utf-8")

