"""Readers: app logs (all quirks), CSV, npz, chunking, errors, the real logs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.sources.readers import ReaderError, detect_format, iter_chunks, read_log_data

# ---------------------------------------------------------------- generated app logs

ACC_OFFSET_MS = 131_072_000


def app_log_lines() -> tuple[list[str], dict]:
    """A log with every quirk: unsorted lines, ACC on a clock 131 072 s ahead, corrupted
    lines, an ORI line with 3 values, non-motion tags. Returns (lines, expectations)."""
    lines = []
    n = 60
    for k in range(n):
        t = 500_000 + 10 * k
        group = [f"{t + 2}\tGYR\t{0.01 * k}\t0.0\t0.0",
                 f"{t + ACC_OFFSET_MS}\tACC\t0.0\t0.0\t{9.0 + 0.01 * k}"]
        if k % 3 == 0:
            group.append(f"{t - 4}\tMAG\t0.0\t20.0\t-40.0")   # stamped earlier, arrives later
        if k % 2:
            group.reverse()
        lines += group
    lines.insert(5, f"{500_020}\tRAWGYR\t0.1\t0.2\t0.3\t0.0\t0.0\t0.0\t0.1\t0.2")  # 8 values
    lines.insert(9, f"{500_030}\tRAWGYR\t0.1\t0.2")               # 2 values -> bad (RAWGYR: 3 or 6)
    lines.insert(12, "")
    lines.insert(20, f"{500_100}\tGYR\t0.1\tabc\t0.3")
    lines.insert(30, f"{500_150}\tWHAT\t1\t2\t3")
    lines.insert(40, f"{500_205}\tORI\t0.1\t0.2\t0.3")           # 3 values: w computed
    lines.insert(41, "1666000000000\tGPS\t58.4\t15.6\t80.0")     # Unix-epoch clock
    lines.insert(50, f"{500_300}\tPRX\t5.0")
    lines.insert(52, f"{500_310}\tORI\t0.8\t0.8\t0.6")           # x²+y²+z² = 1.64: no attitude
    lines.insert(54, f"{500_320}\tORI\t2\t0\t0\t0")             # |q| = 2: no attitude
    expect = dict(acc=n, gyr=n, mag=len(range(0, n, 3)), ori=1,
                  malformed={"wrong_count": 2, "empty": 1, "not_numeric": 1, "unknown_tag": 1,
                             "impossible": 2})
    return lines, expect


def write_log(path, lines, ending="\n"):
    path.write_bytes((ending.join(lines) + ending).encode("ascii"))
    return path


def check_log_data(rec, expect):
    assert rec.kind == "applog"
    n_acc = int(np.sum(~np.isnan(rec.acc[:, 0])))
    n_gyr = int(np.sum(~np.isnan(rec.gyr[:, 0])))
    n_mag = int(np.sum(~np.isnan(rec.mag[:, 0])))
    assert (n_acc, n_gyr, n_mag) == (expect["acc"], expect["gyr"], expect["mag"])
    assert len(rec) == expect["acc"] + expect["gyr"] + expect["mag"] + expect["ori"]
    # exactly one sensor per row
    has = np.stack([~np.isnan(rec.acc[:, 0]), ~np.isnan(rec.gyr[:, 0]), ~np.isnan(rec.mag[:, 0]),
                    ~np.isnan(rec.ori[:, 0])], axis=1)
    assert np.all(has.sum(axis=1) == 1)
    assert np.all(np.diff(rec.t) >= 0), "rows must be in time order"
    assert rec.t[-1] - rec.t[0] < 1.0, "ACC must be mapped onto the GYR/MAG clock"
    assert rec.counts["malformed"] == expect["malformed"]
    assert rec.counts["offsets_s"]["ACC"] == pytest.approx(131_072.0, abs=0.02)
    assert rec.counts["offsets_s"]["GPS"] > 1e9
    assert rec.counts["late"] == 0
    # ORI with 3 values: w = sqrt(1 - x² - y² - z²)
    ori = rec.ori[~np.isnan(rec.ori[:, 0])]
    np.testing.assert_allclose(ori, [[math.sqrt(1 - 0.14), 0.1, 0.2, 0.3]])
    # the ACC value of step k is 9 + 0.01 k, in order of time
    accz = rec.acc[~np.isnan(rec.acc[:, 2]), 2]
    np.testing.assert_allclose(accz, 9.0 + 0.01 * np.arange(expect["acc"]))


@pytest.mark.parametrize("ending", ["\n", "\r\n", "\r"], ids=["lf", "crlf", "cr"])
def test_app_log_with_all_quirks(tmp_path, ending):
    lines, expect = app_log_lines()
    path = write_log(tmp_path / "sensorLog_x.txt", lines, ending)
    assert detect_format(path) == "applog"
    check_log_data(read_log_data(path), expect)


def test_app_log_detected_by_content_not_extension(tmp_path):
    lines, expect = app_log_lines()
    path = write_log(tmp_path / "recording.csv", lines)
    check_log_data(read_log_data(path), expect)


def test_app_log_chunks_concatenate_to_the_whole(tmp_path):
    lines, expect = app_log_lines()
    path = write_log(tmp_path / "log.txt", lines)
    whole = read_log_data(path)
    chunks = list(iter_chunks(path, rows=7))
    assert all(len(c) <= 7 for c in chunks) and len(chunks) == math.ceil(len(whole) / 7)
    np.testing.assert_array_equal(np.concatenate([c.t for c in chunks]), whole.t)
    np.testing.assert_array_equal(np.concatenate([c.acc for c in chunks]), whole.acc)
    assert chunks[-1].counts == whole.counts
    assert chunks[-1].done == 1.0


def test_chunks_are_produced_lazily(tmp_path):
    """The first chunk is ready long before the file is consumed (bounded memory)."""
    lines = [f"{1000 + 5 * k}\tACC\t0.0\t0.0\t9.81" for k in range(20_000)]
    path = write_log(tmp_path / "long.txt", lines)
    first = next(iter_chunks(path, rows=1000))
    assert len(first) == 1000 and first.done < 0.2


# ---------------------------------------------------------------- CSV

def test_csv_with_empty_cells_nan_inf_and_malformed_rows(tmp_path):
    text = ("t,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z,note\r\n"
            "0.00,0,0,9.81,0.1,0.2,0.3,a\r\n"
            "0.01,,,,0.1,0.2,0.3,b\r\n"          # acc missing
            "0.02,nan,0,9.81,inf,0,-inf,c\r\n"   # nan passes through; inf is impossible
            "0.025,0,0,9.81,3000,0,0,f\r\n"     # a gyroscope of 3000 rad/s: impossible
            "0.03,0,0,9.81,0.1\r\n"              # wrong count: skipped
            "0.04,0,zero,9.81,0.1,0.2,0.3,d\r\n"  # text in a number cell: skipped
            "\r\n"
            "0.05,1,2,3,4,5,6,e\r\n")
    path = tmp_path / "rec.csv"
    path.write_text(text, newline="")
    rec = read_log_data(path)
    assert rec.kind == "csv"
    np.testing.assert_array_equal(rec.t, [0.0, 0.01, 0.02, 0.025, 0.05])
    assert np.isnan(rec.acc[1]).all()
    # an impossible reading is refused, its row kept: infinite, so the estimator says "invalid"
    # in that row (before: NaN, "absent", and counted as a skipped line that was not skipped)
    assert np.isnan(rec.acc[2, 0]) and np.isinf(rec.gyr[2]).all() and np.isinf(rec.gyr[3]).all()
    np.testing.assert_array_equal(rec.acc[3], [0, 0, 9.81])
    np.testing.assert_array_equal(rec.gyr[4], [4, 5, 6])
    assert np.isnan(rec.mag).all() and rec.mag.shape == (5, 3)
    assert rec.ori is None
    assert rec.counts["malformed"] == {"wrong_count": 1, "not_numeric": 1}
    assert rec.counts["impossible"] == 2
    from app.estimators import Reason, make_estimator
    from app.estimators.base import F_GYR
    res = make_estimator("robust").run(rec.t, rec.gyr, rec.acc, rec.mag)
    assert [int(x) for x in res.flags[2:4, F_GYR]] == [Reason.INVALID, Reason.INVALID]


def test_csv_with_ori_and_columns_in_any_order(tmp_path):
    path = tmp_path / "rec.dat"
    path.write_text("mag_z,mag_y,mag_x,ori_w,ori_x,ori_y,ori_z,t\n"
                    "-40,20,1,1,0,0,0,0.5\n"
                    "-41,21,2,0,1,0,0,0.6\n")
    rec = read_log_data(path)
    np.testing.assert_array_equal(rec.t, [0.5, 0.6])
    np.testing.assert_array_equal(rec.mag, [[1, 20, -40], [2, 21, -41]])
    np.testing.assert_array_equal(rec.ori, [[1, 0, 0, 0], [0, 1, 0, 0]])
    assert np.isnan(rec.acc).all() and np.isnan(rec.gyr).all()


def test_csv_chunks(tmp_path):
    path = tmp_path / "rec.csv"
    rows = "\n".join(f"{k / 100},0,0,9.81" for k in range(1000))
    path.write_text("t,acc_x,acc_y,acc_z\n" + rows + "\n")
    chunks = list(iter_chunks(path, rows=300))
    assert [len(c) for c in chunks] == [300, 300, 300, 100]
    np.testing.assert_allclose(np.concatenate([c.t for c in chunks]), np.arange(1000) / 100)
    assert chunks[-1].counts["rows"] == 1000


def test_csv_header_only_gives_an_empty_recording(tmp_path):
    path = tmp_path / "rec.csv"
    path.write_text("t,gyr_x,gyr_y,gyr_z\n")
    rec = read_log_data(path)
    assert len(rec) == 0 and rec.gyr.shape == (0, 3)


@pytest.mark.parametrize("content, message", [
    ("time,acc_x,acc_y,acc_z\n0,0,0,9.81\n", "no 't' column"),
    ("t,acc_x,acc_y\n0,0,0\n", "none of acc_x"),
    ("t,foo,bar\n0,1,2\n", "none of acc_x"),
    ("hello world\nthis is text\n", "unknown format"),
    ("", "empty file"),
])
def test_unreadable_files_raise_a_clear_error(tmp_path, content, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(ReaderError, match=message) as e:
        read_log_data(path)
    assert "\n" not in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(ReaderError, match="no such file"):
        read_log_data(tmp_path / "nope.csv")


# ---------------------------------------------------------------- npz

def test_npz_with_t_and_extra_keys(tmp_path):
    rng = np.random.default_rng(0)
    acc, gyr, mag = rng.normal(size=(3, 50, 3))
    t = np.linspace(0, 1, 50)
    path = tmp_path / "rec.npz"
    np.savez(path, acc=acc, gyr=gyr, mag=mag, t=t, opt_quat=np.ones((50, 4)),
             movement=np.ones(50, bool))
    rec = read_log_data(path)
    assert rec.kind == "npz" and rec.ori is None
    np.testing.assert_array_equal(rec.t, t)
    np.testing.assert_array_equal(rec.acc, acc)
    np.testing.assert_array_equal(rec.gyr, gyr)
    np.testing.assert_array_equal(rec.mag, mag)


def test_npz_with_fs_and_without_mag_in_chunks(tmp_path):
    acc = np.tile([0.0, 0.0, 9.81], (25, 1))
    gyr = np.zeros((25, 3))
    path = tmp_path / "rec.bin"          # no .npz extension: detected by content
    with open(path, "wb") as fh:
        np.savez_compressed(fh, acc=acc, gyr=gyr, fs=np.float64(100.0))
    chunks = list(iter_chunks(path, rows=10))
    assert [len(c) for c in chunks] == [10, 10, 5]
    np.testing.assert_allclose(np.concatenate([c.t for c in chunks]), np.arange(25) / 100.0)
    assert all(np.isnan(c.mag).all() for c in chunks)


@pytest.mark.parametrize("arrays, message", [
    (dict(acc=np.zeros((5, 3))), "neither 't'"),
    (dict(t=np.arange(5.0), foo=np.zeros((5, 3))), "none of the arrays"),
    (dict(t=np.arange(5.0), acc=np.zeros((5, 2))), "shape"),
    (dict(t=np.arange(4.0), acc=np.zeros((5, 3))), "4 values for 5 rows"),
])
def test_bad_npz(tmp_path, arrays, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(ReaderError, match=message):
        read_log_data(path)


# ---------------------------------------------------------------- real data

def test_real_logs_read_in_order(real_log):
    rec = read_log_data(real_log)
    assert rec.kind == "applog" and len(rec) > 1000
    assert np.all(np.diff(rec.t) >= 0)
    tags = rec.counts["tags"]
    motion = sum(tags.get(k, 0) for k in ("ACC", "GYR", "MAG", "ORI"))
    assert len(rec) == motion                     # nothing late, nothing lost
    assert rec.counts["late"] == 0
    assert int(np.sum(~np.isnan(rec.acc[:, 0]))) == tags["ACC"]
    expected_bad = {"wrong_count": 2} if "standstill" in real_log.name else {}
    assert rec.counts["malformed"] == expected_bad
    assert rec.counts["lines"] == sum(tags.values()) + sum(expected_bad.values())
    # values in m/s² (not g, not mg): about gravity, larger while running
    assert 8.0 < np.nanmedian(np.linalg.norm(rec.acc, axis=1)) < 16.0


def test_standstill_log_has_two_corrupted_rawgyr_lines(shared_dir):
    path = (shared_dir / "data" / "sensorfusion-app" / "alekodu_activityrecognition"
            / "sensorLog_20221024T182616_standstill.txt")
    if not path.is_file():
        pytest.skip("standstill log absent")
    rec = read_log_data(path)
    assert rec.counts["malformed"] == {"wrong_count": 2}
    assert rec.counts["tags"]["RAWGYR"] == 2632
    # a block of ~23 lines was written ~0.9 s early in this file: it is put back in place
    assert np.all(np.diff(rec.t) >= 0) and np.max(np.diff(rec.t)) < 0.05


def test_broad_npz(shared_dir):
    path = shared_dir / "data" / "broad" / "01_undisturbed_slow_rotation_A.npz"
    if not path.is_file():
        pytest.skip("BROAD data absent")
    rec = read_log_data(path)
    raw = np.load(path)
    assert len(rec) == raw["acc"].shape[0]
    np.testing.assert_allclose(np.diff(rec.t), 1.0 / float(raw["fs"]))
    np.testing.assert_array_equal(rec.mag, raw["mag"])


def test_an_over_long_line_in_a_log_is_counted_and_the_rest_read(tmp_path):
    """A run of bytes without a line end longer than any line of the format (a binary
    blob pasted in) is one malformed line: the lines around it are all read."""
    from app.sources.readers import MAX_LINE_BYTES
    good = [f"{1000 + 10 * k}\tACC\t0.1\t0.2\t9.8" for k in range(50)]
    path = tmp_path / "blob.txt"
    path.write_bytes(("\n".join(good[:20]) + "\n").encode() + b"z" * (3 * MAX_LINE_BYTES)
                     + ("\n" + "\n".join(good[20:]) + "\n").encode())
    rec = read_log_data(path)
    assert len(rec) == 50
    assert rec.counts["malformed"] == {"too_long": 1}


# ---------------------------------------------------------------- whole-file read = line by line

def _line_by_line(path):
    from app.sources.readers import concat
    return concat(list(iter_chunks(path)))


def _same_log_data(a, b):
    """Bit for bit the same rows, and the same counts in the same key order."""
    assert a.kind == b.kind
    for k in ("t", "gyr", "acc", "mag"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.shape == y.shape and x.dtype == y.dtype, k
        np.testing.assert_array_equal(x.view(np.int64), y.view(np.int64), err_msg=k)
    assert (a.ori is None) == (b.ori is None)
    if a.ori is not None:
        np.testing.assert_array_equal(a.ori.view(np.int64), b.ori.view(np.int64))

    def items(d):
        return [(k, items(v) if isinstance(v, dict) else
                 ("nan" if isinstance(v, float) and math.isnan(v) else v)) for k, v in d.items()]
    assert items(a.counts) == items(b.counts)


@pytest.mark.parametrize("ending", ["\n", "\r\n", "\r"], ids=["lf", "crlf", "cr"])
def test_whole_file_read_of_the_quirks_log_is_the_line_by_line_read(tmp_path, ending):
    from app.sources.readers import _applog_whole
    lines, expect = app_log_lines()
    path = write_log(tmp_path / "log.txt", lines, ending)
    fast = _applog_whole(path)
    assert fast is not None, "a log with only in-window disorder takes the vectorised path"
    _same_log_data(fast, _line_by_line(path))
    check_log_data(read_log_data(path), expect)


def _damaged_log(seed: int) -> bytes:
    """A plausible log with every kind of damage a line can have, at random."""
    rng = np.random.default_rng(seed)
    out = []
    t = 200_000 + int(rng.integers(0, 10_000))
    for k in range(1500):
        t += int(rng.integers(1, 6))
        tag = ["ACC", "GYR", "MAG", "ORI", "RAWGYR", "GPS", "PRX", "TXT"][
            int(rng.choice(8, p=[.27, .27, .15, .15, .06, .04, .03, .03]))]
        n = {"ACC": 3, "GYR": 3, "MAG": 3, "ORI": 4, "RAWGYR": 6, "GPS": 3, "PRX": 1, "TXT": 1}[tag]
        stamp = t - int(rng.integers(0, 40))             # a little out of order
        vals = [f"{v:.7g}" for v in rng.normal(0, 5, n)]
        if tag == "TXT":
            vals = ["hello world"]
        r = rng.random()
        if r < 0.02:
            vals[int(rng.integers(n))] = str(rng.choice(["NaN", "Infinity", "-Infinity", "abc", "",
                                                         "1.2.3", "1e", "+", "1_0", " 4.5 ",
                                                         "1e999", "0x10", "-0", "5.", ".5e-3",
                                                         "9" * 40, "1.234567890123456789"]))
        elif r < 0.03:
            vals = vals[:-1]                              # a value missing
        elif r < 0.035:
            vals = vals + [""]                            # a stray tab at the end
        elif r < 0.04:
            vals[0] = "3000"                              # impossible for GYR/MAG/ACC
        elif r < 0.045 and tag == "ORI":
            vals = vals[:3]                               # ORI with x y z only
        ts = str(stamp)
        r = rng.random()
        if r < 0.01:
            ts = rng.choice([f"{stamp}.7", f"0{stamp}", f"{stamp}e0", "x12", "", "-5", "1e99",
                             f" {stamp}", "123456789012345678"])
        line = ts + "\t" + tag + "\t" + "\t".join(vals)
        r = rng.random()
        if r < 0.005:
            line = line.replace("\t", " ")                # spaces instead of tabs
        elif r < 0.01:
            line = ""
        elif r < 0.012:
            line = "   "
        elif r < 0.014:
            line = line + "\u00e9"
        elif r < 0.016:
            line = f"{stamp}\tWHAT\t1\t2\t3"
        out.append(line)
    text = "\n".join(out)
    if seed % 3 == 1:
        text = text.replace("\n", "\r\n")
    data = text.encode("utf-8")
    if seed % 4 == 2:
        data += b"\n"
    if seed % 5 == 3:                                     # an over-long line
        cut = len(data) // 2
        cut = data.index(b"\n", cut)
        data = data[:cut] + b"\n" + b"7" * 70_000 + data[cut:]
    return data


@pytest.mark.parametrize("seed", range(12))
def test_whole_file_read_of_a_damaged_log_is_the_line_by_line_read(tmp_path, seed):
    """Every damaged line is accepted or counted by the same reason, every good one kept
    with the same bits, in the same order, with the same counts."""
    from app.sources.readers import _applog_whole
    path = tmp_path / "damaged.txt"
    path.write_bytes(_damaged_log(seed))
    fast = _applog_whole(path)
    slow = _line_by_line(path)
    assert sum(slow.counts["malformed"].values()) > 10
    if fast is not None:
        _same_log_data(fast, slow)
    _same_log_data(read_log_data(path), slow)


def test_damaged_logs_mostly_take_the_vectorised_path(tmp_path):
    from app.sources.readers import _applog_whole
    taken = 0
    for seed in range(12):
        path = tmp_path / f"d{seed}.txt"
        path.write_bytes(_damaged_log(seed))
        taken += _applog_whole(path) is not None
    assert taken >= 10


def test_a_clock_jump_leaves_the_log_to_the_orderer_a_lone_glitch_does_not(tmp_path):
    """Where the orderer re-anchors its clock, the whole-file read gives way to it; one
    wrong time stamp (+10 s, or 2.8 s back) is only that sample dropped, on the fast
    path too. The same result either way."""
    from app.sources.readers import _applog_whole
    good = [f"{10_000 + 10 * k}\tACC\t0.1\t0.2\t9.8" for k in range(500)]
    jump = good[:200] + [f"{60_000 + 10 * k}\tACC\t0.1\t0.2\t9.8" for k in range(100)]
    path = write_log(tmp_path / "jump.txt", jump)
    assert _applog_whole(path) is None
    _same_log_data(read_log_data(path), _line_by_line(path))
    assert read_log_data(path).counts["jumps"] == 1
    for name, bad in (("ahead", 20_000 + 10 * 100), ("back", 10_000 + 10 * 100 - 2800)):
        lines = good[:100] + [f"{bad}\tACC\t0.1\t0.2\t9.8"] + good[101:]
        path = write_log(tmp_path / f"{name}.txt", lines)
        fast = _applog_whole(path)
        assert fast is not None and fast.counts["malformed"] == {"time_jump": 1}
        assert len(fast) == 499
        _same_log_data(fast, _line_by_line(path))


@pytest.mark.parametrize("seed", range(30))
def test_vectorised_ordering_is_the_orderers_for_any_window(seed):
    """The reordering of the whole-file read against SampleOrderer itself, with short
    windows (where samples do come late: then it must decline), tag clocks, glitches."""
    from app.sources.samples import Sample
    from app.sources.readers import _TAG_ID, _TAGS, _order_like_orderer
    from app.sources.ordering import SampleOrderer
    rng = np.random.default_rng(seed)
    tags = ["ACC", "GYR", "MAG", "GPS", "PRX"]
    clock = {"ACC": 0, "GYR": 0, "MAG": 0, "GPS": 0, "PRX": 0}
    if seed % 3 == 0:
        clock["ACC"] = 131_072_000
    if seed % 2:
        clock["GPS"] = 1_666_000_000_000
    samples, t = [], 50_000
    jitter_ms = [5, 60, 400][seed % 3]
    for _ in range(400):
        t += int(rng.integers(0, 8))
        tag = tags[int(rng.choice(5, p=[.3, .3, .2, .1, .1]))]
        stamp = t + clock[tag] - int(rng.integers(0, jitter_ms))
        if rng.random() < 0.005:
            stamp += int(rng.choice([-5000, 9000, 30_000]))
        samples.append(Sample(stamp, tag, (0.0, 0.0, 0.0)))
    window = [0.0, 0.05, 0.3, 2.0, 2.0][seed % 5]
    o = SampleOrderer(window=window)
    out = [x for s in samples for x in o.push(s)] + o.flush()
    got = _order_like_orderer(np.array([_TAG_ID[s.tag] for s in samples]),
                              np.array([s.time_ms for s in samples], dtype=np.int64),
                              SampleOrderer(window=window))
    c = o.counters
    simple = c.late == 0 and c.clamped == 0 and c.jumps == 0
    if got is None:
        return
    assert simple
    mapped, glitch, offsets, first, popped_at = got
    order = np.flatnonzero(~glitch)[np.argsort(mapped[~glitch], kind="stable")]
    assert [(s.time_ms, s.tag) for s in out] == [(int(mapped[i]), samples[i].tag) for i in order]
    assert {_TAGS[k]: v / 1000.0 for k, v in offsets.items()} == o.offsets
    assert int(glitch.sum()) == c.malformed.get("time_jump", 0)


def test_real_logs_whole_file_read_is_the_line_by_line_read(real_log):
    from app.sources.readers import _applog_whole
    fast = _applog_whole(real_log)
    assert fast is not None
    _same_log_data(fast, _line_by_line(real_log))


def test_a_logs_lines_held_in_memory_give_the_files_rows(real_log):
    """rows_of_lines (a log with a disturbance injected, not on disk) puts the samples in
    order as reading the file does."""
    from app.sources.readers import rows_of_lines
    rows, rec = rows_of_lines(real_log.read_bytes().splitlines()), read_log_data(real_log)
    for k in ("t", "gyr", "acc", "mag"):
        np.testing.assert_array_equal(getattr(rows, k), getattr(rec, k), err_msg=k)


def test_an_ori_reading_with_negative_w_is_read_with_w_positive(tmp_path):
    """q and -q are one attitude; the convention is w >= 0, and each source gives it so at its
    edge (the Sensor Fusion app's ORI lines kept the phone's sign): the line decoder, the
    vectorised whole-file read and a live TCP line alike."""
    from collections import Counter

    from app.sources.readers import _applog_whole
    from app.sources.sensorfusion import decode_lines
    lines = []
    for k in range(40):
        t = 100_000 + 10 * k
        lines += [f"{t}\tACC\t0.1\t0.2\t9.8", f"{t + 1}\tGYR\t0.01\t0.0\t0.0",
                  f"{t + 2}\tMAG\t0.0\t20.0\t-40.0", f"{t + 3}\tORI\t-0.5\t0.5\t-0.5\t0.5"]
    path = write_log(tmp_path / "log.txt", lines)
    for rec in (_applog_whole(path), _line_by_line(path)):
        ori = rec.ori[np.all(np.isfinite(rec.ori), axis=1)]
        assert len(ori) == 40
        np.testing.assert_allclose(ori, np.tile([0.5, -0.5, 0.5, -0.5], (40, 1)))
    samples = decode_lines([ln.encode() for ln in lines[:4]], Counter())
    assert [s.values for s in samples if s.tag == "ORI"] == [(0.5, -0.5, 0.5, -0.5)]
