"""The ``orientlab`` command end to end, in a subprocess (``python -m app.cli``)."""

from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app import quaternion as qm
from app.cli import main
from app.estimators import FLAG_COLUMNS, NAMES, Reason, TimeIssue

REPO = Path(__file__).resolve().parents[1]
THROUGHPUT = re.compile(r"^(\d+) samples in (\d+\.\d+) s \((\d+) samples/s\)$")
REASONS = {r.label for r in Reason}
TIME_ISSUES = {r.name.lower() for r in TimeIssue}


def run_cli(*args, check_rc: int | None = 0) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    if check_rc is not None:
        assert proc.returncode == check_rc, proc.stderr
    return proc


def read_output(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def check_output(path: Path, n_expected: int) -> np.ndarray:
    """Header, row count, unit quaternions, no NaN anywhere; returns q (N, 4)."""
    header, rows = read_output(path)
    assert header == ["t", "qw", "qx", "qy", "qz", *FLAG_COLUMNS]
    assert len(rows) == n_expected
    assert "nan" not in path.read_text().lower()
    q = np.array([[float(v) for v in r[1:5]] for r in rows]).reshape(-1, 4)
    assert np.all(np.isfinite(q))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    col = {name: i for i, name in enumerate(header)}
    for r in rows:
        assert r[col["gyr"]] in REASONS and r[col["acc"]] in REASONS and r[col["mag"]] in REASONS
        assert r[col["time"]] in TIME_ISSUES and r[col["rest"]] in ("0", "1")
        for k in ("acc_value", "acc_nis", "mag_value", "mag_nis"):
            assert r[col[k]] == "" or math.isfinite(float(r[col[k]]))
    return q


def throughput(stderr: str) -> tuple[int, float, int]:
    last = stderr.strip().splitlines()[-1]
    m = THROUGHPUT.match(last)
    assert m, f"last stderr line is not the throughput line: {last!r}"
    return int(m.group(1)), float(m.group(2)), int(m.group(3))


def motion(n: int = 600, fs: float = 100.0, seed: int = 0):
    """Rotation about a slowly changing axis; acc/mag consistent with it plus noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    w = np.stack([0.5 * np.sin(0.7 * t), 0.3 * np.cos(0.5 * t), 0.4 * np.ones(n)], axis=1)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    acc, mag = np.empty((n, 3)), np.empty((n, 3))
    for k in range(n):
        R = qm.Q(q)
        acc[k] = R.T @ [0.0, 0.0, 9.81]
        mag[k] = R.T @ [0.0, 15.0, -45.0]
        q = qm.normalize(qm.quat_mul(q, qm.quat_from_rotvec(w[k] / fs)))
    return (t, w + rng.normal(0, 0.002, (n, 3)), acc + rng.normal(0, 0.05, (n, 3)),
            mag + rng.normal(0, 0.3, (n, 3)))


def write_csv(path: Path, t, gyr, acc, mag, extra_lines=()):
    lines = ["t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"]
    for k in range(len(t)):
        vals = [t[k], *gyr[k], *acc[k], *mag[k]]
        lines.append(",".join("" if (isinstance(v, float) and v != v and k % 2) else repr(float(v))
                              for v in vals))
    lines[5:5] = list(extra_lines)
    path.write_text("\n".join(lines) + "\n")
    return path


def bad_rows(t, gyr, acc, mag):
    """NaN, inf, zero vectors and time going backwards in the middle of good data."""
    t, gyr, acc, mag = t.copy(), gyr.copy(), acc.copy(), mag.copy()
    gyr[50] = np.nan
    acc[51] = [np.inf, 0.0, 9.8]
    mag[52] = 0.0
    acc[53] = np.nan
    gyr[54] = [np.nan, 1.0, np.nan]
    t[60] = t[40]                # backwards
    t[61] = t[60]                # repeated
    t[100:] += 5.0               # a gap
    return t, gyr, acc, mag


# ---------------------------------------------------------------- estimate

@pytest.mark.parametrize("name", NAMES)
def test_estimate_csv_one_row_per_input_row_even_with_bad_rows(tmp_path, name):
    t, gyr, acc, mag = bad_rows(*motion())
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    out = tmp_path / "out.csv"
    proc = run_cli("estimate", src, "--out", out, "--filter", name)
    check_output(out, len(t))
    _, rows = read_output(out)
    np.testing.assert_allclose([float(r[0]) for r in rows], t, atol=1e-6)
    assert throughput(proc.stderr)[0] == len(t)
    # 'phone' on a recording without the phone's own orientation says why it shows nothing
    assert ("has no ORI" in proc.stderr) == (name == "phone")


def test_estimate_follows_the_motion(tmp_path):
    """Not just any unit quaternion: the default filter tracks the true rotation."""
    t, gyr, acc, mag = motion(n=1500)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    out = tmp_path / "out.csv"
    run_cli("estimate", src, "--out", out)
    q = check_output(out, len(t))
    # the true gravity direction in the sensor frame is acc without noise: compare "up"
    up_est = np.array([qm.Q(qk).T @ [0, 0, 1] for qk in q[-200:]])
    up_true = acc[-200:] / np.linalg.norm(acc[-200:], axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, axis=1), -1, 1)))
    assert np.median(angle) < 5.0


def test_malformed_csv_rows_are_skipped_and_counted(tmp_path):
    t, gyr, acc, mag = motion(n=100)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag,
                    extra_lines=["0.033,1,2", "0.034,a,b,c,d,e,f,g,h,i"])
    out = tmp_path / "out.csv"
    proc = run_cli("estimate", src, "--out", out, "--filter", "lab")
    check_output(out, len(t))
    assert "2 malformed lines skipped" in proc.stderr
    quiet = run_cli("estimate", src, "--out", out, "--filter", "lab", "--quiet")
    assert len(quiet.stderr.strip().splitlines()) == 1
    throughput(quiet.stderr)


@pytest.mark.parametrize("timebase", ["t", "fs"])
def test_estimate_npz(tmp_path, timebase):
    t, gyr, acc, mag = bad_rows(*motion(n=300))
    src = tmp_path / "in.npz"
    extra = {"t": t} if timebase == "t" else {"fs": 100.0}
    np.savez(src, gyr=gyr, acc=acc, mag=mag, opt_quat=np.zeros((len(t), 4)), **extra)
    out = tmp_path / "out.csv"
    proc = run_cli("estimate", src, "--out", out, "--chunk", "70")
    check_output(out, len(t))
    assert throughput(proc.stderr)[0] == len(t)


def test_chunked_run_equals_one_run(tmp_path):
    """Estimator state carries over from chunk to chunk."""
    t, gyr, acc, mag = motion(n=400)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    run_cli("estimate", src, "--out", a, "--chunk", "37")
    run_cli("estimate", src, "--out", b, "--chunk", "100000")
    assert a.read_text() == b.read_text()


@pytest.mark.parametrize("name", NAMES)
def test_estimate_real_logs(real_log, name, tmp_path, capsys):
    """Every real log with every estimator. In-process (``app.cli.main``, the very code
    the console script runs) to spare 36 interpreter starts; the tests above cover the
    process boundary."""
    out = tmp_path / "out.csv"
    assert main(["estimate", str(real_log), "--out", str(out), "--filter", name]) == 0
    stderr = capsys.readouterr().err
    n, seconds, rate = throughput(stderr)
    check_output(out, n)
    _, rows = read_output(out)
    ts = np.array([float(r[0]) for r in rows])
    assert np.all(np.diff(ts) >= 0)
    if "standstill" in real_log.name:
        assert "2 malformed lines skipped (wrong_count: 2)" in stderr


def test_set_and_config(tmp_path):
    t, gyr, acc, mag = motion(n=200)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    out = tmp_path / "out.csv"
    # JSON values (number, list) and a plain string value
    run_cli("estimate", src, "--out", out, "--filter", "lab", "--set", "gyr_std=0.02",
            "--set", "time_update=approx", "--set", "g0=[0,0,9.8]")
    check_output(out, len(t))
    preset = tmp_path / "p.toml"
    preset.write_text('primary = "lab"\n[lab]\nacc_std = 0.3\n')
    run_cli("estimate", src, "--out", out, "--config", preset)
    check_output(out, len(t))
    # the preset's primary and parameter were used: same as saying them explicitly
    explicit = tmp_path / "explicit.csv"
    run_cli("estimate", src, "--out", explicit, "--filter", "lab", "--set", "acc_std=0.3")
    assert out.read_text() == explicit.read_text()
    default = tmp_path / "default.csv"
    run_cli("estimate", src, "--out", default)
    assert out.read_text() != default.read_text()


@pytest.mark.parametrize("setting, field", [
    ("gyr_std=5", "gyr_std"),                # out of range
    ("acc_std=abc", "acc_std"),              # not a number
    ("gyr_noise=0.01", "gyr_noise: was renamed gyr_std"),  # lab's former name
    ("no_such_param=1", "no_such_param"),    # unknown
    ("time_update=fast", "time_update"),     # not a choice
])
def test_bad_set_exits_2_naming_the_field(tmp_path, setting, field):
    t, gyr, acc, mag = motion(n=20)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    out = tmp_path / "out.csv"
    proc = run_cli("estimate", src, "--out", out, "--filter", "lab", "--set", setting,
                   check_rc=2)
    assert len(proc.stderr.strip().splitlines()) == 1
    assert field in proc.stderr and proc.stderr.startswith("orientlab: error:")
    assert not out.exists()


def test_bad_config_exits_2(tmp_path):
    preset = tmp_path / "p.toml"
    preset.write_text("[lab]\nacc_std = -1\n")
    proc = run_cli("estimate", "x.csv", "--out", tmp_path / "o.csv", "--config", preset,
                   check_rc=2)
    assert "acc_std" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_old_preset_with_a_renamed_key_still_loads(tmp_path):
    """lab's acc_noise is now acc_std (the same per-sample σ): an old preset is read
    with a warning naming the new key, and gives the same output as the new name."""
    t, gyr, acc, mag = motion(n=200)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    old, new = tmp_path / "old.toml", tmp_path / "new.toml"
    old.write_text('primary = "lab"\n[lab]\nacc_noise = 0.3\n')
    new.write_text('primary = "lab"\n[lab]\nacc_std = 0.3\n')
    out_old, out_new = tmp_path / "old.csv", tmp_path / "new.csv"
    proc = run_cli("estimate", src, "--out", out_old, "--config", old)
    assert "acc_noise was renamed acc_std in lab" in proc.stderr
    run_cli("estimate", src, "--out", out_new, "--config", new)
    assert out_old.read_text() == out_new.read_text()


@pytest.mark.parametrize("content", ["just some text\nnothing else\n", "t,foo\n1,2\n", None])
def test_unknown_format_missing_columns_or_file_exit_2(tmp_path, content):
    src = tmp_path / "in.txt"
    if content is not None:
        src.write_text(content)
    out = tmp_path / "out.csv"
    proc = run_cli("estimate", src, "--out", out, check_rc=2)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("orientlab: error:") and str(src) in lines[0]
    assert not out.exists()
    assert not list(tmp_path.glob(".orientlab-*"))     # no temporary file left behind


# ---------------------------------------------------------------- calibrate, help

def test_calibrate_writes_a_preset_estimate_accepts(tmp_path):
    rng = np.random.default_rng(1)
    n = 1000
    q = qm.normalize(np.array([0.9, 0.3, -0.2, 0.1]))
    R = qm.Q(q)
    t = np.arange(n) / 100.0
    acc = R.T @ [0, 0, 9.81] + rng.normal(0, 0.05, (n, 3))
    gyr = np.array([0.01, -0.02, 0.003]) + rng.normal(0, 0.002, (n, 3))
    mag = R.T @ [0, 15.0, -45.0] + rng.normal(0, 0.3, (n, 3))
    src = write_csv(tmp_path / "still.csv", t, gyr, acc, mag)
    preset = tmp_path / "preset.toml"
    proc = run_cli("calibrate", src, "--out", preset)
    assert "accelerometer (m/s²)" in proc.stdout and "stationary: yes" in proc.stdout
    text = preset.read_text(encoding="utf-8")
    assert "[lab]" in text and "[robust]" in text
    m0 = re.search(r"^m0 = \[(.*)\]$", text, re.M).group(1)
    np.testing.assert_allclose([float(v) for v in m0.split(",")], [0, 15, -45], atol=0.3)
    out = tmp_path / "out.csv"
    run_cli("estimate", src, "--out", out, "--filter", "lab", "--config", preset)
    check_output(out, n)


def test_help_texts():
    top = run_cli("--help")
    for cmd in ("estimate", "calibrate", "serve"):
        assert cmd in top.stdout
    est = run_cli("estimate", "--help").stdout
    for opt in ("--out", "--filter", "--config", "--set", "--quiet"):
        assert opt in est
    serve = run_cli("serve", "--help").stdout
    for opt in ("--host", "--port", "--viewer-port", "--phone-port", "--config", "--source"):
        assert opt in serve
    run_cli("calibrate", "--help")
    assert run_cli(check_rc=2).returncode == 2          # no command: usage error


def test_console_script_is_installed():
    """The ``orientlab`` command beside the interpreter running the tests (whichever venv
    the user made: it looked in ``.venv`` only, and skipped in any other)."""
    exe = Path(sys.executable).parent / "orientlab"
    if not exe.exists():
        pytest.skip(f"console script not installed beside {sys.executable}")
    proc = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "estimate" in proc.stdout


def test_serve_starts_prints_the_addresses_and_stops_cleanly_on_ctrl_c():
    """`orientlab serve` as a user runs it: the banner names the page and the phone port,
    the API answers, and Ctrl-C (SIGINT) ends the process with status 0."""
    import signal
    import time
    import urllib.request

    from harness import free_ports

    port, viewer, phone = free_ports(3)
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1",
                             "--port", str(port), "--viewer-port", str(viewer),
                             "--phone-port", str(phone), "--source", "demo"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, proc.stdout.read()
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            assert time.monotonic() < deadline, "the server did not come up"
            time.sleep(0.3)
        import websockets.sync.client           # a viewer of the 3D view connects
        with websockets.sync.client.connect(f"ws://127.0.0.1:{viewer}", open_timeout=10):
            time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert f"http://127.0.0.1:{port}/" in out
    assert f"port {phone}" in out
    assert "no phone can reach it" in " ".join(out.split())   # --host 127.0.0.1
    # the banner only: not viser's own box of its address (a teacher opened that one), nor
    # a line per viewer's connection
    assert "╭" not in out and "Websocket" not in out, out
    assert "connection open" not in out, out


def test_estimate_into_a_folder_is_one_line_and_the_csv_is_readable_by_others(tmp_path):
    """``--out`` naming a folder gave a traceback (os.replace's IsADirectoryError) and exit
    1; now one line naming it, exit 2. And the CSV is written with the umask's permissions,
    as any file (mkstemp's 0600 kept it from the other users of a shared lab PC)."""
    t, gyr, acc, mag = motion(n=20)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    folder = tmp_path / "results"
    folder.mkdir()
    proc = run_cli("estimate", src, "--out", folder, check_rc=2)
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert str(folder) in proc.stderr and proc.stderr.startswith("orientlab: error:")
    assert [p.name for p in folder.iterdir()] == [] and not list(tmp_path.glob(".orientlab-*"))
    out = tmp_path / "out.csv"
    old = os.umask(0o022)
    try:
        run_cli("estimate", src, "--out", out)
    finally:
        os.umask(old)
    assert out.stat().st_mode & 0o777 == 0o644


def test_out_naming_the_input_is_refused_and_the_recording_kept(tmp_path):
    """A review: ``estimate REC --out REC`` (a slip of the shell's history) replaced the
    recording by the output CSV, exit 0; ``calibrate`` likewise by the preset, and the
    events file given as --config too. Now one line, exit 2, every input unchanged."""
    t, gyr, acc, mag = motion(n=50)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    before = src.read_bytes()
    link = tmp_path / "same.csv"
    link.symlink_to(src)
    for args in (("estimate", src, "--out", src), ("estimate", src, "--out", link),
                 ("calibrate", src, "--out", src, "--force"),
                 ("gyro-scale", src, "--out", src)):
        proc = run_cli(*args, check_rc=2)
        assert "Traceback" not in proc.stderr and "would be replaced" in proc.stderr, (args, proc.stderr)
        assert src.read_bytes() == before, args
    events = tmp_path / "x.events.jsonl"
    events.write_text('{"event": "start"}\n')
    proc = run_cli("estimate", src, "--config", events, "--out", events, check_rc=2)
    assert "would be replaced" in proc.stderr and events.read_text() == '{"event": "start"}\n'
    state = tmp_path / "x.state.npz"          # the recording's state: read too, never written
    state.write_bytes(b"state")
    proc = run_cli("estimate", src, "--config", events, "--out", state, check_rc=2)
    assert "would be replaced" in proc.stderr and state.read_bytes() == b"state"


@pytest.mark.parametrize("arrays", [
    {"acc": np.array(["a", "b"]), "gyr": np.zeros((2, 3)), "fs": 100.0},
    {"acc": np.zeros((2, 3)), "gyr": np.zeros((2, 3)), "fs": "abc"},
    {"acc": np.zeros((2, 3)), "gyr": np.zeros((2, 3)), "t": np.array(["x", "y"])},
    {"acc": np.array([{}, 1], dtype=object), "gyr": np.zeros((2, 3)), "fs": 100.0},
], ids=["text-acc", "text-fs", "text-t", "objects"])
def test_an_npz_of_text_or_objects_is_one_line_exit_2(tmp_path, arrays):
    """A review: an npz whose arrays hold text or objects gave a ValueError traceback
    (exit 1) in estimate, calibrate and gyro-scale; now one line naming the array."""
    src = tmp_path / "bad.npz"
    np.savez(src, **arrays)
    for cmd, out in (("estimate", "x.csv"), ("calibrate", "x.toml"), ("gyro-scale", "x.toml")):
        proc = run_cli(cmd, src, "--out", tmp_path / out, check_rc=2)
        assert "Traceback" not in proc.stderr and "does not hold numbers" in proc.stderr, (cmd, proc.stderr)


def test_an_events_file_with_lines_that_are_no_events_is_one_line_exit_2(tmp_path):
    """``[1, 2]`` or ``"x"`` on a line of an events file (JSON, but no event) gave an
    AttributeError traceback; such lines are skipped as malformed ones are."""
    t, gyr, acc, mag = motion(n=20)
    src = write_csv(tmp_path / "in.csv", t, gyr, acc, mag)
    events = tmp_path / "x.events.jsonl"
    events.write_text('[1, 2]\n"x"\n')
    proc = run_cli("estimate", src, "--config", events, "--out", tmp_path / "o.csv", check_rc=2)
    assert "Traceback" not in proc.stderr and "no 'start' event" in proc.stderr, proc.stderr


def test_ctrl_c_while_the_command_loads_is_one_line():
    """A review: Ctrl-C in the first half second of ``orientlab serve`` (while the command
    line imports numpy and numba) printed a 30-line KeyboardInterrupt traceback. The
    entry point imports it behind a guard: one line, exit 130, as later."""
    import signal
    import time
    proc = subprocess.Popen([sys.executable, "-m", "app", "compile", "--help"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    maps = Path(f"/proc/{proc.pid}/maps")
    deadline = time.monotonic() + 30
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            if "numpy" in maps.read_text():        # inside the command line's import
                break
        except OSError:
            pass
        time.sleep(0.002)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert "Traceback" not in err, err
    assert proc.returncode == 130 and err.strip() == "orientlab: interrupted", (proc.returncode, err)
