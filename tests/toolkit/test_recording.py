"""The recorder (app/toolkit/recording.py): the log is the stream in the app's format, the
estimates and parameters sit beside it, segments end cleanly, failures are messages."""

from __future__ import annotations

import os
from collections import Counter

import numpy as np
import pytest

from app.cli import main as cli_main
from app.estimators import make_estimator
from app.sources.readers import read_log_data
from app.sources.sensorfusion import decode_lines
from app.toolkit.recording import Recorder, RecordingError, RecordingLimits
from app.toolkit.recorded import read_estimates, read_events, recording_files, scan_recordings

LOG = "alekodu_activityrecognition/sensorLog_20221024T182635_walking_hand.txt"


def _samples(lines):
    return decode_lines(lines, Counter())


def test_the_log_is_the_stream_and_reads_like_the_original(tmp_path, shared_dir):
    src = shared_dir / "data" / "sensorfusion-app" / LOG
    lines = src.read_bytes().splitlines()
    rec = Recorder(tmp_path, "take1", limits=RecordingLimits(estimates_hz=0))
    rec.start({"robust": {"gyr_noise": 0.005}}, label="phone")
    for i in range(0, len(lines), 97):
        rec.write_samples(_samples(lines[i:i + 97]))
    r0 = read_log_data(src)
    res = make_estimator("robust").run(r0.t, r0.gyr, r0.acc, r0.mag, r0.ori)
    tags = ["ACC"] * len(r0)
    rec.count_samples(r0.t)
    rec.write_estimates("robust", r0.t, tags, res.q, res.flags)
    rec.write_estimates("truth", r0.t[:10], "ORI", res.q[:10])
    rec.note("params", t=float(r0.t[100]), params={"robust": {"gyr_noise": 0.01}},
             mark=(int(r0.t[100] * 1000), "parameters changed: robust.gyr_noise=0.01"))
    out = rec.stop()
    assert out["name"] == "take1" and out["samples"] == len(r0)
    assert out["seconds"] == pytest.approx(r0.t[-1] - r0.t[0], abs=1e-3)
    log = tmp_path / "take1.txt"
    body = log.read_bytes()
    # the stream's samples, written again: the same readings, bit for bit
    head = src.read_bytes().replace(b"\r\n", b"\n")[:1000].splitlines()[:-1]
    assert _samples(body.splitlines()[:len(head)]) == _samples(head)
    r1 = read_log_data(log)
    for k in ("t", "gyr", "acc", "mag", "ori"):
        np.testing.assert_array_equal(getattr(r1, k), getattr(r0, k))
    # the CLI reads it as any app log
    assert cli_main(["estimate", str(log), "--out", str(tmp_path / "o.csv"), "-q"]) == 0
    est = read_estimates(tmp_path / "take1.estimates.csv.gz")
    np.testing.assert_allclose(est["robust"]["q"], res.q, atol=1e-8)
    assert len(est["truth"]["t"]) == 10
    ev = read_events(tmp_path / "take1.events.jsonl")
    assert [e["kind"] for e in ev] == ["start", "params", "end"]
    assert ev[0]["params"]["robust"]["gyr_noise"] == 0.005
    assert ev[1]["params"]["robust"]["gyr_noise"] == 0.01 and ev[1]["t"] == pytest.approx(r0.t[100])
    listed = {r["name"]: r for r in scan_recordings(tmp_path)[0]}
    assert listed["take1"]["orientlab"] and listed["take1"]["samples"] == len(r0)
    assert "o" in listed                                        # a CSV dropped in is listed too


def test_a_disconnect_ends_the_segment_and_the_next_stream_gets_its_own(tmp_path):
    rec = Recorder(tmp_path, "lesson")
    rec.start({}, label="phone A")
    rec.write_samples(_samples([b"1000\tACC\t0\t0\t9.81", b"1010\tACC\t0\t0\t9.81"]))
    rec.count_samples(np.array([1.0, 1.01]))
    rec.end_segment("phone disconnected")
    assert rec.active and rec.segment is None
    rec.write_samples(_samples([b"5\tACC\t0\t0\t9.81"]))                   # between streams: nothing
    rec.new_segment("phone B")
    rec.write_samples(_samples([b"20\tACC\t0\t0\t9.8"]))
    out = rec.stop()
    assert [s["name"] for s in out["segments"]] == ["lesson", "lesson_2"]
    assert out["segments"][0]["end_reason"] == "phone disconnected"
    assert (tmp_path / "lesson.txt").read_bytes() == b"1000\tACC\t0\t0\t9.81\n1010\tACC\t0\t0\t9.81\n"
    assert (tmp_path / "lesson_2.txt").read_bytes() == b"20\tACC\t0\t0\t9.8\n"
    assert read_events(tmp_path / "lesson.events.jsonl")[-1]["reason"] == "phone disconnected"
    assert recording_files(tmp_path, "lesson_2")["events"] is not None


def test_a_name_is_one_recording_and_every_file_left_out_says_why(tmp_path):
    """Files dropped in the recordings folder by hand: each name is listed once (two logs
    of one name had crashed the page's menus), with the log the downloads and the
    replay take; a file that looks like a log but is left out is named with why; a new
    recording or segment never takes a name a dropped log has."""
    line = b"1000\tACC\t0\t0\t9.81\n"
    for f in ("dup.csv", "dup.txt", "dup.log", "UPPER.TXT", "a..b.txt", "My Log.txt",
              "_under.txt", "lab2.csv", "seg_2.csv", "ok.npz"):
        (tmp_path / f).write_bytes(line)
    (tmp_path / "empty.txt").write_bytes(b"")
    (tmp_path / "notes.md").write_bytes(line)          # not a log's extension: not named
    os.utime(tmp_path / "ok.npz", (1e9, 1e9))             # the oldest
    listed = scan_recordings(tmp_path)[0]
    names = [r["name"] for r in listed]
    assert sorted(names) == ["UPPER", "dup", "lab2", "ok", "seg_2"] and names[-1] == "ok"
    by = {r["name"]: r for r in listed}
    assert by["dup"]["path"].endswith("dup.txt")
    for name, f in (("dup", "dup.txt"), ("UPPER", "UPPER.TXT"), ("lab2", "lab2.csv")):
        assert recording_files(tmp_path, name)["log"].name == f
    left = {x["file"]: x["why"] for x in scan_recordings(tmp_path)[1]}
    assert set(left) == {"dup.csv", "dup.log", "a..b.txt", "My Log.txt", "_under.txt", "empty.txt"}
    assert "dup.txt, listed" in left["dup.csv"] and "not a recording name" in left["My Log.txt"]
    assert left["empty.txt"] == "empty"
    with pytest.raises(RecordingError, match="exists already"):
        Recorder(tmp_path, "lab2").start({}, label="phone")
    rec = Recorder(tmp_path, "seg")
    rec.start({}, label="phone A")
    rec.write_samples(_samples([line.strip()]))
    rec.new_segment("phone B")                          # seg_2 is a dropped log's name
    rec.write_samples(_samples([line.strip()]))
    assert [g["name"] for g in rec.stop()["segments"]] == ["seg", "seg_3"]
    parts = {r["name"]: r for r in scan_recordings(tmp_path)[0]}
    assert (parts["seg_3"]["recording"], parts["seg_3"]["segment"]) == ("seg", 2)
    assert (parts["seg"]["recording"], parts["seg"]["segment"]) == ("seg", 1)
    assert parts["seg_3"]["complete"] and parts["seg_3"]["end_reason"] == "stopped"
    assert (parts["seg_2"]["recording"], parts["seg_2"]["orientlab"]) == ("seg_2", False)


def test_a_file_name_that_is_not_utf8_is_shown_and_an_empty_log_keeps_its_name(tmp_path):
    """A zip from another system leaves Latin-1 names: listed as left out, its name
    readable as text (its lone surrogates had made the API's answer a 500). A log left
    empty (a crash before the first write) still holds its name: a new recording of that
    name is refused, as before, not moved to NAME_2."""
    import json
    raw = os.fsencode(tmp_path) + b"/mesure_\xe9t\xe9.txt"
    with open(raw, "wb") as fh:
        fh.write(b"1000\tACC\t0\t0\t9.81\n")
    listed, left = scan_recordings(tmp_path)
    assert listed == [] and left[0]["file"] == "mesure_\ufffdt\ufffd.txt", left
    json.dumps(left).encode("utf-8")                      # what the API sends
    (tmp_path / "lesson.txt").write_bytes(b"")
    with pytest.raises(RecordingError, match="exists already"):
        Recorder(tmp_path, "lesson").start({}, label="phone")
    # a file is found by its own name, not by one built here (a case-insensitive disk
    # opens Walk.TXT for walk.txt)
    (tmp_path / "Walk.TXT").write_bytes(b"1000\tACC\t0\t0\t9.81\n")
    (tmp_path / "walk.csv").write_bytes(b"t,ax\n0,1\n")
    assert recording_files(tmp_path, "walk")["log"].name == "walk.csv"
    assert recording_files(tmp_path, "Walk")["log"].name == "Walk.TXT"


def test_the_listing_finds_the_end_of_a_long_events_file(tmp_path):
    """A long class's events file holds every change; the listing (twice a second on
    the page) reads its first line and its last 64 kB, and finds the end event there."""
    rec = Recorder(tmp_path, "long")
    rec.start({"robust": {"gyr_noise": 0.005}}, label="phone")
    rec.write_samples(_samples([b"1000\tACC\t0\t0\t9.81"]))
    rec.count_samples(np.array([1.0]))
    for k in range(3000):
        rec.note("params", params={"robust": {"gyr_noise": 0.005 + k * 1e-6, "pad": "x" * 200}})
    rec.stop()
    assert (tmp_path / "long.events.jsonl").stat().st_size > 600_000
    r = scan_recordings(tmp_path)[0][0]
    assert r["complete"] and r["samples"] == 1 and r["orientlab"] and r["recording"] == "long"


def test_an_unwritable_folder_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RecordingError, match="cannot create the recordings folder"):
        Recorder(blocker / "recordings", "a").start({})
    rec = Recorder(tmp_path, "dup")
    rec.start({})
    rec.write_samples(_samples([b"1000\tACC\t0\t0\t9.81"]))     # an empty one is removed
    rec.stop()
    with pytest.raises(RecordingError, match="exists already"):
        Recorder(tmp_path, "dup").start({})
    with pytest.raises(RecordingError, match="invalid recording name"):
        Recorder(tmp_path, "../etc")


def test_a_full_disk_stops_the_recording_with_a_message_and_raises_nothing(tmp_path):
    # the estimates file (gzip) goes to /dev/full: writes fail with ENOSPC as on a full disk
    os.symlink("/dev/full", tmp_path / "full.estimates.csv.gz")
    rec = Recorder(tmp_path, "full", flush_every_s=0.0)
    rec.start({})
    for k in range(200):
        rec.write_samples(_samples([f"{1000 + k}\tACC\t0\t0\t9.81".encode()]))
        rec.write_estimates("robust", np.array([k * 0.01]), "ACC", np.array([[1.0, 0, 0, 0]]))
    assert rec.error is not None and "disk is full" in rec.error
    assert not rec.active
    out = rec.stop()
    assert out["error"] == rec.error
    assert (tmp_path / "full.txt").read_bytes().startswith(b"1000\tACC")
