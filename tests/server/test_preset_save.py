"""One save path for every preset: the dashboard's "save" (``POST /api/presets/save``)
and a calibration's ``save_as`` (``POST /api/calibrate/apply``, ``POST /api/magcal/apply``)
both go through :func:`app.server.presets.write_preset`.

The first version saved a calibration's preset beside the checks: it could take a
shipped preset's name, ignored ``Settings.max_presets``, wrote the file in place (a
failed write left half a preset) and a folder refusing the write gave a 500. Real
server, real HTTP requests; the folder is really made unwritable (a read-only folder,
a path through a regular file, a file-size limit on the server's process).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from app.params import CONFIG_DIR
from app.server.presets import shipped_names
from harness import free_ports, running_server, wait_for

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
SHIPPED = sorted(shipped_names())


def write_still_csv(path: Path, n: int = 600, fs: float = 100.0, seed: int = 3) -> None:
    """A phone lying still: gravity and a field plus sensor noise (the calibration's input)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    acc = np.array([0.05, -0.02, 9.81]) + rng.normal(0.0, 0.03, (n, 3))
    gyr = np.array([0.002, -0.001, 0.003]) + rng.normal(0.0, 0.001, (n, 3))
    mag = np.array([12.0, 18.0, -40.0]) + rng.normal(0.0, 0.4, (n, 3))
    cols = ["t"] + [f"{s}_{a}" for s in ("acc", "gyr", "mag") for a in "xyz"]
    rows = np.column_stack([t, acc, gyr, mag])
    path.write_text(",".join(cols) + "\n"
                    + "".join(",".join(f"{v:.6f}" for v in r) + "\n" for r in rows))


def calibrated(api) -> None:
    """A calibration from the still recording (what "apply" then uses)."""
    r = api.post("/api/calibrate", json={"recording": "still"})
    assert r.status_code == 200, r.text


def msg(r) -> str:
    return " ".join(d["msg"] for d in r.json()["detail"])


def leftovers(folder: Path) -> list[str]:
    """Anything in the preset folder that is not a finished preset."""
    return sorted(p.name for p in folder.iterdir() if not p.name.endswith(".toml")
                  or p.name.startswith("."))


@pytest.fixture
def lab(tmp_path):
    rec = tmp_path / "recordings"
    rec.mkdir()
    write_still_csv(rec / "still.csv")
    presets = tmp_path / "presets"
    with running_server(recordings=rec, preset_dir=presets, max_presets=4) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        calibrated(api)
        yield s, api, presets


# ---------------------------------------------------------------- shipped names

def test_a_calibration_preset_cannot_take_a_shipped_name(lab):
    s, api, presets = lab
    assert "default" in SHIPPED
    before = {n: (CONFIG_DIR / f"{n}.toml").read_bytes() for n in SHIPPED}
    acc_before = api.get("/api/params").json()["estimators"]["lab"]["acc_std"]
    for name in SHIPPED:
        r = api.post("/api/calibrate/apply", json={"save_as": name})
        assert r.status_code == 422, (name, r.status_code, r.text)
        assert "shipped" in msg(r) and r.json()["detail"][0]["loc"] == ["body", "save_as"]
        r = api.post("/api/magcal/apply", json={"clear": True, "save_as": name})
        assert r.status_code == 422, (name, r.status_code, r.text)
        assert "shipped" in msg(r)
    # a refused name applies nothing, writes nothing; the shipped files are untouched
    assert api.get("/api/params").json()["estimators"]["lab"]["acc_std"] == acc_before
    assert not presets.exists() or not any(presets.iterdir())
    assert {n: (CONFIG_DIR / f"{n}.toml").read_bytes() for n in SHIPPED} == before
    # the name rules hold there too
    for name in ("../evil", "x\n", "a/b", "n" * 65):
        r = api.post("/api/calibrate/apply", json={"save_as": name})
        assert r.status_code == 422, (name, r.status_code)
    assert not (REPO / "evil.toml").exists() and not (presets.parent / "evil.toml").exists()


# ---------------------------------------------------------------- the cap

def test_the_cap_counts_and_limits_calibration_presets(lab):
    s, api, presets = lab
    assert s.settings.max_presets == 4
    for k in range(2):
        assert api.post("/api/presets/save", json={"name": f"p{k}"}).status_code == 200
    for k in range(2):
        r = api.post("/api/calibrate/apply", json={"save_as": f"cal{k}"})
        assert r.status_code == 200, r.text
    assert sorted(p.name for p in presets.iterdir()) == ["cal0.toml", "cal1.toml", "p0.toml",
                                                         "p1.toml"]
    # full: a new name is refused on every path, with the reason
    r = api.post("/api/calibrate/apply", json={"save_as": "cal2"})
    assert r.status_code == 422 and "already 4 saved presets" in msg(r), r.text
    r = api.post("/api/magcal/apply", json={"clear": True, "save_as": "cal2"})
    assert r.status_code == 422 and "already 4 saved presets" in msg(r), r.text
    r = api.post("/api/presets/save", json={"name": "p2"})
    assert r.status_code == 422 and "already 4 saved presets" in msg(r), r.text
    assert len(list(presets.iterdir())) == 4
    # an existing name is overwritten (not a new preset)
    assert api.post("/api/calibrate/apply", json={"save_as": "p0"}).status_code == 200
    assert api.post("/api/presets/save", json={"name": "cal1"}).status_code == 200
    assert len(list(presets.iterdir())) == 4


# ---------------------------------------------------------------- a folder refusing the write

@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` made unwritable: its mode, and for root (whom modes do not stop) the
    immutable attribute. None if this machine cannot make it so."""
    folder.mkdir(parents=True, exist_ok=True)
    mode = folder.stat().st_mode
    folder.chmod(0o555)
    immutable = False
    try:
        if os.geteuid() == 0 and shutil.which("chattr"):
            immutable = subprocess.run(["chattr", "+i", str(folder)],
                                       capture_output=True).returncode == 0
        probe = folder / ".probe"
        try:
            probe.write_text("x")
            probe.unlink()
            unwritable = False
        except OSError:
            unwritable = True
        yield folder if unwritable else None
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(mode)


def test_a_read_only_preset_folder_is_a_clear_refusal(lab):
    s, api, presets = lab
    with read_only(presets) as ro:
        if ro is None:
            pytest.skip("cannot make a folder read-only here")
        for path, body in (("/api/calibrate/apply", {"save_as": "cal"}),
                           ("/api/magcal/apply", {"clear": True, "save_as": "cal"}),
                           ("/api/presets/save", {"name": "cal"})):
            r = api.post(path, json=body)
            assert r.status_code == 507, (path, r.status_code, r.text)
            text = msg(r)
            assert "cannot write the preset 'cal'" in text and str(presets) in text, text
            assert "denied" in text.lower() or "not permitted" in text.lower(), text
        assert list(presets.iterdir()) == []
    # writable again: the same request saves
    assert api.post("/api/calibrate/apply", json={"save_as": "cal"}).status_code == 200


def test_a_preset_folder_that_cannot_exist_is_a_clear_refusal(tmp_path):
    """A path through a regular file (refused even to root)."""
    rec = tmp_path / "recordings"
    rec.mkdir()
    write_still_csv(rec / "still.csv")
    (tmp_path / "afile").write_text("not a folder")
    bad = tmp_path / "afile" / "presets"
    with running_server(recordings=rec, preset_dir=bad) as s, \
            httpx.Client(base_url=s.url, timeout=60.0) as api:
        calibrated(api)
        r = api.post("/api/calibrate/apply", json={"save_as": "cal"})
        assert r.status_code == 507, r.text
        assert "cannot write the preset 'cal'" in msg(r) and "Not a directory" in msg(r), r.text
        r = api.post("/api/presets/save", json={"name": "cal"})
        assert r.status_code == 507 and "Not a directory" in msg(r), r.text
        assert api.get("/api/health").json()["status"] == "ok"


# ---------------------------------------------------------------- complete files

def test_a_calibration_preset_is_complete_and_loads_back(lab):
    s, api, presets = lab
    r = api.post("/api/calibrate/apply", json={"save_as": "cal"})
    assert r.status_code == 200, r.text
    applied = r.json()["applied"]
    path = Path(r.json()["preset"])
    assert path == presets / "cal.toml"
    text = path.read_text()
    assert text.startswith("# orientlab preset from a calibration on the page")
    data = tomllib.loads(text)
    assert data["primary"] in SHIPPED or data["primary"] in api.get("/api/params").json()["bases"]
    for name, params in applied.items():
        for k, v in params.items():
            np.testing.assert_allclose(data[name][k], v, rtol=1e-9, atol=1e-12)
    assert leftovers(presets) == []
    # back to the defaults, then the preset: the calibration's values again
    assert api.post("/api/presets/load", json={"name": "default"}).status_code == 200
    r = api.post("/api/presets/load", json={"name": "cal"})
    assert r.status_code == 200, r.text
    for name, params in applied.items():
        for k, v in params.items():
            np.testing.assert_allclose(r.json()["estimators"][name][k], v, rtol=1e-9, atol=1e-12)


def _serve(tmp_path: Path, rec: Path, presets: Path) -> tuple[subprocess.Popen, str]:
    """``orientlab serve`` in a process of its own (its file-size limit is set below);
    its output to pipes-free /dev/null (not a regular file: no limit applies)."""
    port, viewer_port, phone_port = free_ports(3)
    env = {k: v for k, v in os.environ.items() if k not in ("ORIENTLAB_PRESETS",)}
    env["NUMBA_DISABLE_JIT"] = "1"      # the estimators in Python: no compile wait
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--source", "none", "--open",
         "--host", "127.0.0.1", "--port", str(port), "--viewer-port", str(viewer_port),
         "--phone-port", str(phone_port), "--recordings", str(rec),
         "--presets-dir", str(presets)],
        cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"

    def up():
        if proc.poll() is not None:
            raise AssertionError(f"serve exited {proc.returncode}")
        with contextlib.suppress(httpx.HTTPError):
            return httpx.get(f"{url}/api/health", timeout=2.0).status_code == 200
    wait_for(up, 120.0, 0.2, "serve to answer")
    return proc, url


@pytest.mark.skipif(not hasattr(__import__("resource"), "prlimit"), reason="needs prlimit (Linux)")
def test_a_failed_write_leaves_the_old_preset_whole_and_no_temporary(tmp_path):
    """The write fails half-way (the server's file-size limit, EFBIG): the preset saved
    before is still whole, no temporary is left, the refusal is a 507."""
    import resource
    rec = tmp_path / "recordings"
    rec.mkdir()
    write_still_csv(rec / "still.csv")
    presets = tmp_path / "presets"
    proc, url = _serve(tmp_path, rec, presets)
    try:
        with httpx.Client(base_url=url, timeout=60.0) as api:
            calibrated(api)
            r = api.post("/api/calibrate/apply", json={"save_as": "cal"})
            assert r.status_code == 200, r.text
            good = (presets / "cal.toml").read_bytes()
            assert len(good) > 1000
            r = api.patch("/api/params", json={"use_mag": False})
            assert r.status_code == 200, r.text
            soft, hard = resource.prlimit(proc.pid, resource.RLIMIT_FSIZE)
            resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (200, hard))   # any preset is larger
            try:
                for path, body in (("/api/calibrate/apply", {"save_as": "cal"}),
                                   ("/api/magcal/apply", {"clear": True, "save_as": "cal"}),
                                   ("/api/presets/save", {"name": "cal"})):
                    r = api.post(path, json=body)
                    now = (presets / "cal.toml").read_bytes()
                    assert now == good, f"{path} left the preset {len(now)} of {len(good)} bytes"
                    assert leftovers(presets) == [], path
                    assert r.status_code == 507, (path, r.status_code, r.text)
                    assert "cannot write the preset 'cal'" in msg(r), r.text
            finally:
                resource.prlimit(proc.pid, resource.RLIMIT_FSIZE, (soft, hard))
            # the limit lifted: the new values are saved, whole
            r = api.post("/api/calibrate/apply", json={"save_as": "cal"})
            assert r.status_code == 200, r.text
            saved = tomllib.loads((presets / "cal.toml").read_text())
            now = api.get("/api/params").json()["estimators"]
            assert saved["lab"]["use_mag"] is False and saved["robust"]["use_mag"] is False
            assert set(saved["lab"]) <= set(now["lab"])
            for k, v in saved["lab"].items():
                assert v == now["lab"][k] or np.allclose(v, now["lab"][k], rtol=1e-12), k
            assert leftovers(presets) == []
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
