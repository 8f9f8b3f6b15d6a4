"""docs/filter_evidence.svg and the figures docs/filter.md quotes: robust's heading noise measured
from the data on real trials, beside the heading error it leads to.

First the table of time constants docs/filter.md quotes. Then, for each trial named below (a
phone carried through a building's uneven field, the research IMU carried through a lab), robust
runs in 0.1 s slices and its state is read after each: the field's heading wander (√v, the
evidence of ``heading_evidence_tau``) and the heading noise density it sets with the field's
deviation from its reference (d, ``mag_dev_weight``), √(heading_noise² + 2 (v + d²) · 0.5 s).
Beside them the heading error against the optical truth of robust (defaults), robust with the
evidence off (``heading_evidence_tau=0``, ``mag_dev_weight=0``, ``heading_noise`` 0.15 as before
issue 19's item 2) and VQF (defaults). The figure is plain SVG (no plotting
library); the script prints each trial's RMSE and the share of time the correction ran slower.

Data: ``../shared/data`` (phones: Michel et al., IEEE PerCom 2017, CeCILL 2.1; BROAD: Laidig et
al., Data 6(7):72, 2021, CC-BY-4.0). Usage: ``python docs/make_filter_plot.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy_phones import load_broad, load_phones  # noqa: E402
from app.estimators import make_estimator  # noqa: E402
from app.estimators.robust.heading import evidence_density  # noqa: E402
from app.quaternion import error_angles  # noqa: E402

DEG = 180.0 / np.pi
TRIALS = ("iPhone5_Guillaume_Dist_texting", "10_undisturbed_slow_translation_A")
SLICE_S = 0.1
OUT = ROOT / "docs" / "filter_evidence.svg"


def trace(trial: dict, params: dict | None):
    """Run robust in slices; per slice end: time, √v (rad), the heading noise density (rad·√s)."""
    est = make_estimator("robust", params)
    t = trial["t"]
    edges = np.searchsorted(t, np.arange(t[0], t[-1] + SLICE_S, SLICE_S))
    qs, rows = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        res = est.run(t[a:b], trial["gyr"][a:b], trial["acc"][a:b], trial["mag"][a:b])
        qs.append(res.q)
        d = est.diagnostics()
        rows.append((t[b - 1], d.heading_wander, d.heading_noise_now))
    return np.concatenate(qs), np.array(rows)


def heading_err(q, trial) -> np.ndarray:
    ref = trial["ref"]
    ok = trial["mask"] & np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(q), axis=1)
    h = np.full(len(q), np.nan)
    _, hh, _ = error_angles(q[ok], ref[ok])
    h[ok] = np.abs(hh) * DEG
    return h


def vqf_q(trial) -> np.ndarray:
    from vqf import VQF
    v = VQF(1.0 / trial["fs"])
    return v.updateBatch(*(np.ascontiguousarray(trial[k]) for k in ("gyr", "acc", "mag")))["quat9D"]


# ------------------------------------------------------------------ SVG

W, PANEL_H, PAD_L, PAD_R, PAD_T, GAP = 900, 150, 70, 20, 34, 40
COLORS = {"robust": "#1f77b4", "evidence off": "#ff7f0e", "VQF": "#7f7f7f", "wander": "#2ca02c",
          "density": "#9467bd"}


def _poly(x, y, x0, x1, y0, y1, top, color, width=1.2):
    ok = np.isfinite(y)
    if not ok.any():
        return ""
    step = max(1, int(ok.sum() / 1500))
    xs = PAD_L + (x[ok][::step] - x0) / (x1 - x0) * (W - PAD_L - PAD_R)
    ys = top + PANEL_H - (np.clip(y[ok][::step], y0, y1) - y0) / (y1 - y0) * PANEL_H
    pts = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(xs, ys))
    return f'<polyline fill="none" stroke="{color}" stroke-width="{width}" points="{pts}"/>'


def _axes(top, title, y1, unit, x0, x1):
    out = [f'<text x="{PAD_L}" y="{top - 8}" font-size="13" font-weight="bold">{title}</text>',
           f'<rect x="{PAD_L}" y="{top}" width="{W - PAD_L - PAD_R}" height="{PANEL_H}" fill="none" '
           f'stroke="#999"/>']
    for frac in (0.0, 0.5, 1.0):
        y = top + PANEL_H * (1 - frac)
        out.append(f'<text x="{PAD_L - 6}" y="{y + 4:.1f}" font-size="11" text-anchor="end">'
                   f'{y1 * frac:.3g}{unit}</text>')
    for k in range(6):
        xv = x0 + (x1 - x0) * k / 5
        x = PAD_L + (W - PAD_L - PAD_R) * k / 5
        out.append(f'<text x="{x:.1f}" y="{top + PANEL_H + 13}" font-size="11" text-anchor="middle">'
                   f'{xv:.0f} s</text>')
    return out


def _legend(top, items):
    out, x = [], PAD_L + 10
    for label, color in items:
        out.append(f'<line x1="{x}" y1="{top + 12}" x2="{x + 18}" y2="{top + 12}" stroke="{color}" '
                   f'stroke-width="2"/><text x="{x + 22}" y="{top + 16}" font-size="11">{label}</text>')
        x += 30 + 7 * len(label)
    return out


def time_constants() -> None:
    """The table of docs/filter.md: the heading noise density and the correction's time
    constant (about σ_h / gyr_noise) for a field wandering by √v."""
    prm = make_estimator("robust").params
    print("wander √v (deg)   σ_h (deg·√s)   time constant σ_h/gyr_noise (s)")
    for w in (0.0, 0.5, 3.0, 10.0):
        s_h = np.sqrt(prm.heading_noise ** 2 + evidence_density(np.radians(w) ** 2))
        print(f"{w:15.1f}   {np.degrees(s_h):12.1f}   {s_h / prm.gyr_noise:31.1f}")


def main() -> int:
    time_constants()
    trials = {t["name"]: t for t in load_phones() + load_broad() if t["name"] in TRIALS}
    if len(trials) < len(TRIALS):
        print("the shared data is not here (../shared/data): nothing to plot")
        return 1
    parts, top = [], PAD_T
    for name in TRIALS:
        tr = trials[name]
        q, rows = trace(tr, None)
        q_off, _ = trace(tr, {"heading_evidence_tau": 0.0, "mag_dev_weight": 0.0,
                              "heading_noise": 0.15})
        t = tr["t"][:len(q)]
        h = {"robust": heading_err(q, tr), "evidence off": heading_err(q_off, tr),
             "VQF": heading_err(vqf_q(tr)[:len(q)], tr)}
        rms = {k: float(np.sqrt(np.nanmean(v ** 2))) for k, v in h.items()}
        hn = make_estimator("robust").params.heading_noise
        slower = float(np.mean(rows[:, 2] > 1.5 * hn))
        print(f"{name}: heading RMSE robust {rms['robust']:.2f}°, evidence off {rms['evidence off']:.2f}°, "
              f"VQF {rms['VQF']:.2f}°; field's heading wander √v median {np.median(rows[:, 1]) * DEG:.2f}°, "
              f"95th percentile {np.percentile(rows[:, 1], 95) * DEG:.2f}°; the correction ran ≥ 1.5× "
              f"slower (density ≥ 1.5 × heading_noise) {100 * slower:.0f} % of the time")
        x0, x1 = float(t[0]), float(t[-1])
        y1 = max(2.0, float(np.nanpercentile(rows[:, 2] * DEG, 99)) * 1.1)
        parts += _axes(top, f"{name}: heading noise density (deg·√s) and the field's wander √v (deg)",
                       y1, "", x0, x1)
        parts.append(_poly(rows[:, 0], rows[:, 2] * DEG, x0, x1, 0, y1, top, COLORS["density"]))
        parts.append(_poly(rows[:, 0], rows[:, 1] * DEG, x0, x1, 0, y1, top, COLORS["wander"]))
        parts += _legend(top, [("density √(heading_noise² + 2(v + d²)·0.5 s)", COLORS["density"]),
                               ("wander √v", COLORS["wander"])])
        top += PANEL_H + GAP
        y1 = max(5.0, float(np.nanpercentile(np.concatenate(list(h.values())), 99)) * 1.1)
        parts += _axes(top, f"{name}: heading error against the optical truth (deg), RMSE robust "
                            f"{rms['robust']:.2f}, evidence off {rms['evidence off']:.2f}, VQF {rms['VQF']:.2f}",
                       y1, "°", x0, x1)
        for k in ("VQF", "evidence off", "robust"):
            parts.append(_poly(t, h[k], x0, x1, 0, y1, top, COLORS[k]))
        parts += _legend(top, [(k, COLORS[k]) for k in ("robust", "evidence off", "VQF")])
        top += PANEL_H + GAP
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{top}" '
           f'font-family="sans-serif"><rect width="100%" height="100%" fill="white"/>'
           + "".join(parts) + "</svg>\n")
    OUT.write_text(svg)
    print(f"wrote {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
