"""The live path's estimates, saved and compared: does a reshaping change any estimate?

Streams each real app log (``tests/conftest.py`` REAL_LOGS, read from ``../shared``) the
way the dashboard does: lines in chunks of ``CHUNK`` through a :class:`SampleOrderer`
(window 0.05 s), every released sample one row for every estimator (default
parameters), in order. ``--save DIR`` writes, per log, the estimate of every estimator
after every sample (``q``, (N, 4)) and its flag record; ``--compare DIR`` runs the live
core (:class:`app.live.Ensemble`, one compiled batch run per chunk) on the same chunks and
prints the largest difference per estimator and log (target: < 1e-9).

``--save`` steps every estimator sample by sample as the engine did before the live core
existed (``Estimator.step``). ``--against-step`` compares the live core with that stepping
on the current code (no saved files): the live path changes no estimate, whatever an
estimator's own code is today (another change may improve an estimator: ``--compare``
against files saved before it then shows that change, not the live path's).

Run: ``.venv/bin/python benchmarks/live_equivalence.py --save /tmp/ref``, change the code,
then ``.venv/bin/python benchmarks/live_equivalence.py --compare /tmp/ref``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from conftest import REAL_LOGS, SHARED  # noqa: E402
from app.sources.ordering import SampleOrderer

CHUNK = 40
NAMES = ("robust", "lab", "complementary", "phone")
SENSOR_OF_TAG = {"GYR": "gyr", "ACC": "acc", "MAG": "mag"}


def chunks_of(path: Path) -> list[list]:
    """The samples released per chunk of CHUNK lines (and the final flush)."""
    lines = path.read_bytes().splitlines()
    o = SampleOrderer(window=0.05)
    out = []
    for i in range(0, len(lines), CHUNK):
        rel = []
        for ln in lines[i:i + CHUNK]:
            rel.extend(o.push_line(ln))
        out.append(rel)
    out.append(o.flush())
    return [c for c in out if c]


def run_step(chunks) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Sample by sample through Estimator.step, as the engine did (motion + ORI rows)."""
    from app.estimators import make_estimator
    out = {}
    for name in NAMES:
        est = make_estimator(name)
        qs, fl = [], []
        for chunk in chunks:
            for s in chunk:
                sensor = SENSOR_OF_TAG.get(s.tag)
                if sensor is not None:
                    kw = {sensor: np.array(s.values, dtype=float)}
                elif s.tag == "ORI":
                    kw = {"ori": np.array(s.values, dtype=float)}
                else:
                    continue
                f = est.step(s.time_ms / 1000.0, **kw)
                qs.append(est.q)
                fl.append([f.gyr, f.acc, f.acc_value, f.acc_nis, f.mag, f.mag_value, f.mag_nis,
                           float(f.rest), f.time])
        out[name] = (np.array(qs), np.array(fl, dtype=float))
    return out


def run_ensemble(chunks) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Chunk by chunk through the live core's ensemble (one batch run per estimator)."""
    from app.live.ensemble import Ensemble
    ensemble = Ensemble.from_config(None)
    qs = {n: [] for n in NAMES}
    fl = {n: [] for n in NAMES}
    for chunk in chunks:
        rec = ensemble.step(chunk)
        for n in NAMES:
            r = rec.of(n)
            qs[n].append(r.q)
            fl[n].append(r.flags)
    return {n: (np.concatenate(qs[n]), np.concatenate(fl[n])) for n in NAMES}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--save", type=Path)
    g.add_argument("--compare", type=Path)
    g.add_argument("--against-step", action="store_true")
    args = ap.parse_args()
    base = SHARED / "data" / "sensorfusion-app"
    if not base.is_dir():
        print(f"{base} not present: nothing to do")
        return 0
    worst = 0.0
    for rel in REAL_LOGS:
        path = base / rel
        key = rel.replace("/", "__")
        chunks = chunks_of(path)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            res = run_step(chunks)
            np.savez_compressed(args.save / f"{key}.npz",
                                **{f"{n}_q": v[0] for n, v in res.items()},
                                **{f"{n}_flags": v[1] for n, v in res.items()})
            print(f"saved {rel}: {len(res['robust'][0])} rows")
            continue
        if args.against_step:
            ref = {f"{n}_{k}": v for n, (q, f) in run_step(chunks).items()
                   for k, v in (("q", q), ("flags", f))}
        else:
            ref = np.load(args.compare / f"{key}.npz")
        res = run_ensemble(chunks)
        cells = []
        for n in NAMES:
            q, f = res[n]
            rq, rf = ref[f"{n}_q"], ref[f"{n}_flags"]
            if q.shape != rq.shape:
                cells.append(f"{n} SHAPE {q.shape} vs {rq.shape}")
                worst = np.inf
                continue
            dq = float(np.max(np.abs(q - rq))) if q.size else 0.0
            same_nan = np.array_equal(np.isnan(f), np.isnan(rf))
            df = float(np.nanmax(np.abs(f - rf))) if f.size and same_nan else (0.0 if same_nan else np.inf)
            worst = max(worst, dq, df)
            cells.append(f"{n} |dq| {dq:.1e} |dflags| {df:.1e}")
        print(f"{rel} ({len(res['robust'][0])} rows): " + "; ".join(cells))
    if not args.save:
        print(f"largest difference over all logs, estimators, rows: {worst:.2e} "
              f"({'within' if worst < 1e-9 else 'NOT within'} 1e-9)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
