"""Bounded tools on a real server (issue 21, items 2 and 8): injections capped and cheap
(Ctrl-C still stops the server), recordings capped in duration, size and free space,
no empty files, compact estimates, and watchers never see the presenter's file paths.

Every test runs the real dashboard (tests/harness.py, or ``orientlab serve`` in its own
process) and talks to it with real HTTP and TCP clients."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from app.sources.readers import read_log_data
from app.sources.sensorfusion import format_line
from app.sources.simulate import SimConfig, simulate
from app.toolkit.recorded import EstimatesCutShort, read_estimates, read_events
from harness import Phone, free_ports, running_server, wait_for

ROOT = Path(__file__).resolve().parents[2]
# Ctrl-C ends the server rather than hanging; how fast (about a second) is a benchmark's
# figure (benchmarks/health_latency.py), not this test's: a shared CI machine is noisy
STOP_TIMEOUT_S = 15.0
MAGNET = {"kind": "magnet", "strength_uT": 40, "direction": "east", "seconds": 600}


def _inject_until_refused(api: httpx.Client, most: int = 100) -> tuple[int, httpx.Response | None]:
    """POST magnets until one is refused (or ``most`` are on): (accepted, the refusal)."""
    for k in range(most):
        r = api.post("/api/inject", json=MAGNET)
        if r.status_code != 200:
            return k, r
    return most, None


def _wait_stream(api: httpx.Client) -> None:
    wait_for(lambda: api.get("/api/stats").json().get("samples", 0) > 50, 60.0, 0.1, "the demo")


# ---------------------------------------------------------------- injections

def test_at_most_a_few_injections_are_on_and_one_more_is_refused_with_a_message(tmp_path):
    with running_server(source="demo", recordings=tmp_path, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        _wait_stream(api)
        n, refusal = _inject_until_refused(api, most=20)
        assert refusal is not None, f"{n} disturbances accepted: no cap"
        assert 1 <= n <= 8
        assert refusal.status_code == 409
        text = refusal.text
        assert f"at most {n} disturbances at once" in text and "wait for one to end" in text
        st = api.get("/api/inject").json()
        assert len(st["active"]) == n and st["max_active"] == n
        # health still answers with the most allowed on (how fast: benchmarks/health_latency.py)
        for _ in range(20):
            h = api.get("/api/health")
            assert h.status_code == 200 and h.json()["status"] == "ok"


def test_ctrl_c_stops_the_server_within_seconds_with_the_most_injections_on(tmp_path):
    port, vport, pport = free_ports(3)
    cmd = [sys.executable, "-c", "import sys; from app.cli import main; sys.exit(main())",
           "serve", "--source", "demo", "--open", "--host", "127.0.0.1",
           "--port", str(port), "--viewer-port", str(vport), "--phone-port", str(pport),
           "--recordings", str(tmp_path / "rec"), "--presets-dir", str(tmp_path / "presets")]
    err = open(tmp_path / "stderr.txt", "w+b")
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as api:
            def up():
                try:
                    return api.get("/api/health").status_code == 200
                except httpx.HTTPError:
                    return False
            wait_for(up, 300.0, 0.2, "the server")
            _wait_stream(api)
            n, _ = _inject_until_refused(api, most=100)   # as many as it takes
            time.sleep(2.0)                                 # all on, the demo streaming
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"Ctrl-C did not stop the server within {STOP_TIMEOUT_S:g} s "
                        f"({n} disturbances on)")
        assert rc == 0, (tmp_path / "stderr.txt").read_text(errors="replace")[-2000:]
        assert n <= 8
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        err.close()


# ---------------------------------------------------------------- recordings: bounds

def _status(api):
    return api.get("/api/recordings").json()["status"]


def _find(x, key):
    """Every value of ``key`` anywhere in a JSON value."""
    if isinstance(x, dict):
        return [v for k, v in x.items() if k == key] + [w for v in x.values() for w in _find(v, key)]
    if isinstance(x, list):
        return [w for v in x for w in _find(v, key)]
    return []


def test_a_recording_stops_cleanly_at_its_duration_cap(tmp_path):
    rec = tmp_path / "rec"
    with running_server(source="demo", recordings=rec, preset_dir=tmp_path,
                        recording_max_s=2.0) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        _wait_stream(api)
        r = api.post("/api/recordings/start", json={"name": "capped"})
        assert r.status_code == 200
        # no rate from the header written in the first milliseconds (it said 4.8 MB/s)
        rates = _find(r.json(), "bytes_per_s")
        assert rates and all(v < 1e6 for v in rates), r.text
        time.sleep(0.8)
        st = _status(api)
        assert st["recording"] and st["bytes"] > 0 and st["bytes_per_s"] > 0   # size, rate
        tab = s.app.state.toolkit_tab                  # the page's Lab tab says them too
        wait_for(lambda: "**recording**" in tab.rec_md.content, 10.0, 0.1, "the page")
        assert "B at " in tab.rec_md.content and "B/s" in tab.rec_md.content
        wait_for(lambda: not _status(api)["recording"], 20.0, 0.2, "the duration cap")
        wait_for(lambda: "duration cap" in tab.rec_md.content, 10.0, 0.1, "the page's reason")
        last = _status(api)["last"]
        assert "duration cap" in last["stop_reason"]
        assert 1.5 <= last["elapsed_s"] <= 6.0
        end = read_events(rec / "capped.events.jsonl")[-1]
        assert end["kind"] == "end" and "duration cap" in end["reason"]
        assert (rec / "capped.txt").stat().st_size > 0


def test_a_recording_stops_cleanly_at_its_size_cap(tmp_path):
    rec = tmp_path / "rec"
    cap = 60_000
    with running_server(source="demo", recordings=rec, preset_dir=tmp_path,
                        recording_max_bytes=cap) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        _wait_stream(api)
        assert api.post("/api/recordings/start", json={"name": "big"}).status_code == 200
        wait_for(lambda: not _status(api)["recording"], 60.0, 0.2, "the size cap")
        last = _status(api)["last"]
        assert "size cap" in last["stop_reason"]
        on_disk = sum(p.stat().st_size for p in rec.iterdir())
        assert cap <= on_disk <= cap + 40_000, on_disk      # one chunk past it at most
        assert "size cap" in read_events(rec / "big.events.jsonl")[-1]["reason"]
        listed = {r["name"]: r for r in api.get("/api/recordings").json()["recordings"]}
        assert listed["big"]["complete"]


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MB tmpfs (we run as root in the sandbox), else skipped."""
    d = tmp_path / "small"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(d)],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.decode(errors='replace')}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def test_low_free_space_refuses_a_start_and_stops_a_running_recording(tmp_path, small_disk):
    with running_server(source="demo", recordings=small_disk, preset_dir=tmp_path,
                        recording_min_free_bytes=1_000_000) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        _wait_stream(api)
        assert api.post("/api/recordings/start", json={"name": "lab1"}).status_code == 200
        time.sleep(1.0)
        assert _status(api)["recording"]
        # something else fills the disk: the recording stops before it is full
        filler = small_disk / ".filler"
        filler.write_bytes(b"\0" * 2_300_000)
        wait_for(lambda: not _status(api)["recording"], 20.0, 0.2, "the free-space floor")
        last = _status(api)["last"]
        assert "free space low" in last["stop_reason"] and last["error"] is None
        assert "free space low" in read_events(small_disk / "lab1.events.jsonl")[-1]["reason"]
        # and a new one is refused, saying why
        r = api.post("/api/recordings/start", json={"name": "lab2"})
        assert r.status_code == 507 and "free space low" in r.text
        assert not (small_disk / "lab2.txt").exists()


def test_a_recording_with_no_stream_leaves_no_file_and_none_is_listed(tmp_path):
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "old_empty.txt").write_bytes(b"")      # a 0-byte log left by an older version
    with running_server(recordings=rec, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api:
        assert api.post("/api/recordings/start", json={"name": "nothing"}).status_code == 200
        time.sleep(1.0)
        out = api.post("/api/recordings/stop").json()
        assert [p.name for p in rec.iterdir()] == ["old_empty.txt"]
        assert api.get("/api/recordings").json()["recordings"] == []
        assert out["samples"] == 0 and out.get("empty")
        # a recording started as the stream ended: the same
        with Phone(s.phone_port) as ph:
            ph.send_lines([f"{1000 + 10 * k}\tACC\t0\t0\t9.81" for k in range(50)])
            wait_for(lambda: api.get("/api/stats").json().get("samples", 0) >= 40, 30.0)
        time.sleep(0.5)                              # the phone has gone
        assert api.post("/api/recordings/start", json={"name": "late"}).status_code == 200
        time.sleep(1.0)
        api.post("/api/recordings/stop")
        assert not (rec / "late.txt").exists()
        assert api.get("/api/recordings").json()["recordings"] == []


# ---------------------------------------------------------------- recordings: compact

def _settled(api: httpx.Client, timeout: float = 60.0) -> None:
    """Wait until the server has processed everything sent (its count stops growing)."""
    last = [-1, time.monotonic()]

    def still():
        n = api.get("/api/stats").json().get("samples", 0)
        if n != last[0]:
            last[:] = [n, time.monotonic()]
        return time.monotonic() - last[1] > 1.5
    wait_for(still, timeout, 0.2, "every line processed")


def _phone_500hz(seconds: float):
    cfg = SimConfig(acc_period_ms=2, gyr_period_ms=2, mag_period_ms=2, ori_period_ms=10)
    sim = simulate(duration_s=seconds, config=cfg, seed=3)
    return [format_line(*x) for x in sim.samples]


def test_estimates_are_compact_readable_and_the_full_rate_comes_back_from_the_log(tmp_path):
    rec = tmp_path / "rec"
    lines = _phone_500hz(8.0)
    with running_server(recordings=rec, preset_dir=tmp_path) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as api, Phone(s.phone_port) as ph:
        ph.send_lines(lines[:200])
        wait_for(lambda: api.get("/api/stats").json().get("samples", 0) > 100, 60.0)
        assert api.post("/api/recordings/start", json={"name": "fast"}).status_code == 200
        for i in range(200, len(lines), 1500):          # about real time, 1 s a chunk
            ph.send_lines(lines[i:i + 1500])
            time.sleep(0.25)
        _settled(api)
        out = api.post("/api/recordings/stop").json()
        est_path = rec / "fast.estimates.csv.gz"
        assert est_path.is_file() and not (rec / "fast.estimates.csv").exists()
        assert est_path.read_bytes()[:2] == b"\x1f\x8b"
        est = read_estimates(est_path)
        # a copy cut short (a student's download stopped half-way): the rows up to the cut,
        # and a warning that says the rest is missing (it said nothing)
        cut = tmp_path / "cut.estimates.csv.gz"
        cut.write_bytes(est_path.read_bytes()[:est_path.stat().st_size * 19 // 20])
        with pytest.warns(EstimatesCutShort, match="ends early"):
            part = read_estimates(cut)
        assert 0 < len(part["robust"]["t"]) <= len(est["robust"]["t"])
        assert np.array_equal(part["robust"]["t"], est["robust"]["t"][:len(part["robust"]["t"])])
        log = read_log_data(rec / "fast.txt")
        span = log.t[-1] - log.t[0]
        for name in ("robust", "lab", "complementary"):
            n = len(est[name]["t"])
            assert 0.7 * 20 * span <= n <= 20 * span + 5, (name, n, span)   # ~20 rows/s
            per_s = np.bincount(np.floor(est[name]["t"] - est[name]["t"][0]).astype(int))
            assert per_s.max() <= 21
        # the download is the same file
        r = api.get("/api/recordings/fast/estimates")
        assert r.status_code == 200 and r.content == est_path.read_bytes()
        assert out["bytes"] > 0
    # the full rate: `orientlab estimate` on the log, a row per motion sample
    from app.cli import main as cli_main
    full = tmp_path / "full.csv"
    assert cli_main(["estimate", str(rec / "fast.txt"), "--out", str(full), "--filter", "lab",
                     "-q"]) == 0
    rows = full.read_text().splitlines()[1:]
    assert len(rows) == len(log.t) and len(rows) > 20 * len(est["lab"]["t"])
    t_full = np.array([float(r.split(",", 1)[0]) for r in rows])
    assert t_full[-1] - t_full[0] == pytest.approx(span, abs=0.01)


# ---------------------------------------------------------------- watchers

def test_watchers_see_names_sizes_and_times_but_no_paths(tmp_path):
    rec = tmp_path / "secret_place" / "rec"
    tok = "presenter-token-123"
    with running_server(recordings=rec, preset_dir=tmp_path, open_access=False, token=tok) as s, \
            httpx.Client(base_url=s.url, timeout=30.0) as watcher, \
            httpx.Client(base_url=s.url, timeout=30.0, headers={"X-Orientlab-Token": tok}) as pres, \
            Phone(s.phone_port) as ph:
        ph.send_lines([f"{1000 + 10 * k}\tACC\t0\t0\t9.81" for k in range(100)])
        wait_for(lambda: pres.get("/api/stats").json().get("samples", 0) > 50, 30.0)
        assert pres.post("/api/recordings/start", json={"name": "take"}).status_code == 200
        ph.send_lines([f"{2000 + 10 * k}\tACC\t0\t0\t9.81" for k in range(100)])
        time.sleep(1.0)
        seen = watcher.get("/api/recordings").text        # while recording
        assert str(tmp_path) not in seen and "secret_place" not in seen
        # the page (one Lab tab for every viewer) names recordings, never their paths
        tab = s.app.state.toolkit_tab
        assert "secret_place" not in tab.rec_md.content
        assert all("secret_place" not in str(o) for o in tab.rp_name.options)
        assert pres.post("/api/recordings/stop").status_code == 200
        w = watcher.get("/api/recordings")
        assert w.status_code == 200
        body = w.json()
        text = json.dumps(body)
        assert str(tmp_path) not in text and "secret_place" not in text and '"path"' not in text
        r = next(x for x in body["recordings"] if x["name"] == "take")
        assert r["bytes"] > 0 and r["modified"] > 0                # names, sizes, times
        p = pres.get("/api/recordings").json()                      # the presenter sees paths
        assert any(str(rec) in x["path"] for x in p["recordings"])
        # nor does a refusal: an unknown recording names the folder by its name only
        for url in ("/api/recordings/nope/log", "/api/recordings/nope/estimates"):
            r = watcher.get(url)
            msg = r.json()["detail"][0]["msg"]
            assert r.status_code == 404 and "/" not in msg and "'rec'" in msg, msg
