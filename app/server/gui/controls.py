"""The tuning controls: one per parameter of every estimator, built from the metadata.

Every field of every estimator's ``Params`` gets a control, shown in the user's unit
(``user_unit``/``user_scale`` of :func:`app.params.param`):

- a switch: a checkbox; a choice: a dropdown;
- a quantity tuned over decades (``log=True``, noise levels): a number field showing the
  value itself in its unit (``0.286 deg/s``) with three significant digits;
- a quantity with a short range: a slider whose ends are rounded numbers inside the
  valid range;
- anything else: a number field;
- a vector (``g0``, ``m0``, ``gyr_bias``, ``gyr_scale``): three number fields; an optional one (``m0``:
  learned when not given) is "not given" when all three are 0;
- a covariance (``gyr_cov``...: a 3x3 matrix from calibration) as σ per axis; all 0 means
  "none" (the scalar noise applies). A full matrix from a preset shows the σ of its
  diagonal; editing it replaces the matrix by that diagonal;
- a band (``mag_band_uT``): two fields, low and high; 0 and 0: none.

Each control's hover text says what it is, its unit and what raising it does.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

SIG = 3  # significant digits shown

# What raising a parameter does, by name (the doc string of the field says what it is).
EFFECT = {
    "max_gap": "raise it to integrate across longer pauses of the stream",
    "gyr_hold": "raise it to keep turning with the last rate longer when gyroscope rows are missing",
    "time_update": "",
    "gyr_std": "raising it trusts the gyroscope less: the estimate follows the accelerometer "
                 "and magnetometer faster, and gets noisier",
    "acc_std": "raising it trusts the accelerometer less: tilt is corrected more slowly, "
                 "shakes disturb less",
    "mag_std": "raising it trusts the magnetometer less: heading is corrected more slowly, "
                 "magnets disturb less",
    "gyr_cov": "larger σ on an axis trusts the gyroscope less about that axis",
    "acc_cov": "larger σ on an axis trusts the accelerometer less along that axis",
    "mag_cov": "larger σ on an axis trusts the magnetometer less along that axis",
    "q_rw_noise": "raising it lets the estimate move faster (and noisier) when the gyroscope is off",
    "g0": "the gravity the accelerometer is compared with",
    "m0": "the field the magnetometer is compared with; 0 0 0: learned from the data",
    "gyr_bias": "subtracted from every gyroscope sample: set it to the gyroscope's reading at rest",
    "gyr_scale": "each axis, its bias removed, is divided by 1 + s: set it from orientlab gyro-scale "
                 "(a phone's gyroscope is off by 0.2-3 %)",
    "acc_band_rel": "raising it accepts accelerometer samples farther from |g| "
                    "(fewer rejections during shakes, more tilt error); 0 switches the gate off",
    "mag_band_rel": "raising it accepts field strengths farther from |m0| "
                    "(fewer rejections near magnets, more heading error); 0 switches the gate off",
    "mag_band_uT": "a wider band rejects fewer magnetometer samples; 0 0: use mag_band_rel",
    "mag_alpha": "raising it makes L_k follow the field strength faster (reacts sooner to a magnet, "
                 "noisier)",
    "nis_gate": "raising it rejects fewer updates (only larger innovations are refused); 0: off",
    "p0": "raising it makes the first seconds after alignment follow the sensors harder",
    "m0_learn_time": "raising it averages the field longer before m0 is fixed",
    "gyr_noise": "raising it trusts the gyroscope less: the estimate follows the accelerometer "
                 "and magnetometer faster, and gets noisier",
    "rw_noise": "raising it lets the estimate move faster (and noisier) when the gyroscope is off",
    "rest_lp_tau": "raising it smooths the rest detector's low-passes more (slower to see rest)",
    "mag_cand_tau": "raising it averages a candidate new field longer",
    "mag_nis_reset_time": "raising it keeps refusing heading updates longer before the gate opens",
    "mag_relearn_std": "raising it lets the heading move more after the field is re-learned",
    "init_tilt_std": "raising it lets the first tilt corrections move the estimate more",
    "init_heading_std": "raising it lets the first heading corrections move the estimate more",
    "noacc_tilt_std": "raising it trusts a level start less when there is no accelerometer",
    "bias_noise": "raising it lets the gyroscope bias estimate change faster (noisier bias)",
    "bias_init": "raising it lets the bias estimate move more in the first seconds",
    "tilt_noise": "raising it trusts the accelerometer's gravity direction less: slower tilt "
                  "corrections, smaller errors during accelerations",
    "acc_tau": "raising it averages the accelerometer over longer: motion disturbs tilt less, "
               "tilt corrections lag more",
    "tilt_damping": "raising it makes the tilt loop slower to answer a drifting gyroscope, with less "
                    "overshoot (none from 1); 0: off (overdamped)",
    "heading_noise": "raising it trusts the magnetometer heading less: slower heading corrections",
    "heading_drift_window": "raise it to learn the gyroscope's drift about the vertical from a longer "
                            "stretch of the field (steadier, slower to follow a change); 0 stops "
                            "learning it from the field",
    "heading_drift_corr": "raise it to trust the drift fit less where the field's heading wanders "
                          "(the bias is learned more slowly in a bent field)",
    "refused_turn_noise": "raising it makes the heading jump back sooner when the field returns after "
                          "a long refusal while the phone turned; 0: off (the steady, slow rate)",
    "mag_norm_gate_rel": "raising it accepts field strengths farther from the learned one "
                         "(fewer rejections, magnets disturb more); 0: off",
    "mag_dip_gate": "raising it accepts dip angles farther from the learned one; 0: off",
    "mag_ref_tau": "raising it makes the learned field reference follow slow changes more slowly",
    "mag_new_field_time": "raising it waits longer before a new, stable field is accepted",
    "mag_new_min_rate": "raising it needs faster turning before a new field is accepted",
    "rest_gyr_th": "raising it detects rest while the phone still moves slightly",
    "rest_acc_th": "raising it detects rest while the phone still moves slightly",
    "rest_time": "raising it needs a longer quiet time before 'standstill'; 0: no rest detection",
    "rest_noise": "raising it makes the bias learn more slowly at rest",
    "update_rate_hz": "raising it makes more measurement updates per second (more CPU); 0: every sample",
    "tau": "raising it trusts the gyroscope longer (smoother, but error ≈ gyro bias × τ)",
    "ma_window": "raising it averages more accelerometer/magnetometer samples (smoother, slower)",
    "am_hold": "raising it lets an old accelerometer/magnetometer sample stand in longer",
    "gyro_update": "",
}


def fmt(x: float, sig: int = SIG) -> str:
    """A number with ``sig`` significant digits, no trailing zeros (0.286, 12, 1e-05)."""
    if x == 0 or not math.isfinite(x):
        return "0" if x == 0 else str(x)
    s = f"{x:.{sig}g}"
    if "e" in s:
        m, e = s.split("e")
        return f"{m}e{int(e)}"
    return s


def precision_for(x: float, sig: int = SIG) -> int:
    """Decimals that show ``sig`` significant digits of ``x`` (at most 8)."""
    if x == 0 or not math.isfinite(x):
        return 2
    return max(0, min(8, sig - 1 - math.floor(math.log10(abs(x)))))


def nice_ends(lo: float, hi: float) -> tuple[float, float]:
    """Slider ends: ``lo``/``hi`` rounded inwards to two significant digits (57.29578
    -> 57), so the ends read as plain numbers and stay inside the valid range."""
    def round_in(x, up):
        if x == 0:
            return 0.0
        e = 10.0 ** (math.floor(math.log10(abs(x))) - 1)
        return (math.ceil(x / e) if up else math.floor(x / e)) * e
    a, b = round_in(lo, True), round_in(hi, False)
    return (float(fmt(a)), float(fmt(b))) if a < b else (lo, hi)


def nice_step(span: float) -> float:
    raw = span / 200.0
    e = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 5, 10):
        if raw <= m * e:
            return m * e
    return 10 * e


def hint_text(row: dict[str, Any], kind: str) -> str:
    unit = row["user_unit"] or ""
    doc = row["doc"].rstrip(".")
    parts = [doc[:1].upper() + doc[1:] + "."]
    if kind == "sigma3":
        parts.append(f"Shown as σ per axis in {unit or 'its unit'} (√ of the diagonal); "
                     "all 0: none, the scalar noise applies.")
    elif unit:
        parts.append(f"Unit: {unit}" + (f" (API: {row['unit']})" if row["unit"] != unit else "") + ".")
    effect = EFFECT.get(row["name"], "")
    if effect:
        parts.append(effect[0].upper() + effect[1:] + ".")
    if row.get("default_from"):
        parts.append(f"Default from {row['default_from']}.")
    parts.append(f"API name: {row['name']}.")
    return " ".join(parts)


@dataclass
class Control:
    """One GUI control bound to one parameter of one estimator."""
    estimator: str
    name: str
    handle: Any
    kind: str       # bool, choice, log, linear, number, int, vector, optvec, sigma3, band2
    scale: float = 1.0             # user value = value * scale
    unit: str = ""
    lo: float | None = None        # the valid range (SI), checked in the user's unit
    hi: float | None = None
    shown_at: float = 0.0          # the handle's update_timestamp when this code last set it
    kept: Any = None               # fields typed and refused, left in the box (a half-typed band)

    def typed_recently(self, seconds: float) -> bool:
        """Whether a viewer changed the control in the last ``seconds`` (viser stamps every
        update, a viewer's as soon as it arrives, before the callbacks run; ours are
        known by :attr:`shown_at`)."""
        ts = float(getattr(self.handle, "update_timestamp", 0.0) or 0.0)
        return ts > self.shown_at and time.time() - ts < seconds

    MULTI = ("vector", "optvec", "sigma3", "band2")      # several fields, typed one by one

    # ---------------------------------------------------------------- conversion
    def to_gui(self, value):
        k = self.kind
        if k in ("log", "linear", "number"):
            return value * self.scale
        if k == "int":
            return int(value)
        if k == "vector":
            return tuple(float(v) * self.scale for v in value)
        if k == "optvec":
            return (0.0, 0.0, 0.0) if value is None else tuple(float(v) * self.scale for v in value)
        if k == "band2":
            return (0.0, 0.0) if value is None else tuple(float(v) * self.scale for v in value)
        if k == "sigma3":
            if value is None:
                return (0.0, 0.0, 0.0)
            return tuple(math.sqrt(max(float(value[4 * i]), 0.0)) * self.scale for i in range(3))
        return value

    def from_gui(self, v):
        k = self.kind
        if k in ("log", "linear", "number"):
            return float(v) / self.scale
        if k == "int":
            return int(round(float(v)))
        if k == "vector":
            return tuple(float(x) / self.scale for x in v)
        if k in ("optvec", "band2"):
            vals = tuple(float(x) / self.scale for x in v)
            return None if all(x == 0 for x in vals) else vals
        if k == "sigma3":
            s = [float(x) / self.scale for x in v]
            if all(x == 0 for x in s):
                return None
            out = [0.0] * 9
            for i in range(3):
                out[4 * i] = s[i] ** 2
            return tuple(out)
        return v

    def shown(self, value):
        """What the control shows for ``value`` (SI): a number with SIG significant digits
        (the box takes up to :data:`BOX_DECIMALS` typed), anything else as :meth:`to_gui`
        gives it."""
        v = self.to_gui(value)
        if self.kind in ("log", "number"):
            return float(fmt(v))
        if self.kind in ("vector", "optvec", "sigma3"):
            return tuple(float(fmt(x)) for x in v)
        return v

    RANGED = ("log", "number", "int", "vector", "optvec", "band2")   # lo/hi per number

    def out_of_range(self, value) -> str | None:
        """Why a number typed (SI; each of a vector's or a band's) is outside the valid range,
        in the user's unit; None if inside (the box does not clamp it silently: viser's
        would, on leaving the box)."""
        if self.kind not in self.RANGED or value is None:
            return None
        unit = f" {self.unit}" if self.unit else ""
        for x in (value if isinstance(value, (tuple, list)) else (value,)):
            if x != x:
                continue
            if self.lo is not None and x < self.lo:
                return (f"{self.name}: {fmt(x * self.scale)}{unit} is below the minimum "
                        f"{fmt(self.lo * self.scale)}{unit}")
            if self.hi is not None and x > self.hi:
                return (f"{self.name}: {fmt(x * self.scale)}{unit} is above the maximum "
                        f"{fmt(self.hi * self.scale)}{unit}")
        return None

    def gui_same(self, value) -> bool:
        """Whether the control already shows ``value`` (SI): what it holds is what
        :meth:`shown` gives (a full matrix from a preset shows as its diagonal σ)."""
        return self.holds(self.handle.value, value)

    def holds(self, held, value) -> bool:
        """Whether a control holding ``held`` stands for ``value`` (SI): it shows it
        (:meth:`shown`, 3 digits), or it holds what was typed to give it (0.28654 typed and
        applied: writing 0.287 back into the box under the fingers changed the next keys'
        number)."""
        def eq(a, b) -> bool:
            if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
                return len(a) == len(b) and all(eq(x, y) for x, y in zip(a, b))
            if isinstance(a, (bool, str)) or isinstance(b, (bool, str)) or a is None or b is None:
                return a == b
            return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
        if eq(held, self.shown(value)):
            return True
        try:
            return eq(self.from_gui(held), value)
        except (TypeError, ValueError):
            return False

    def label(self) -> str:
        return f"{self.name} [{self.unit}]" if self.unit and self.kind != "bool" else self.name


def build_control(gui, est_name: str, row: dict[str, Any], value, meta: dict[str, Any],
                  order: float | None = None) -> Control | None:
    """The control for one parameter (``row`` from :func:`app.params.describe`)."""
    name = row["name"]
    scale, unit = float(row["user_scale"] or 1.0), row["user_unit"] or ""
    lo, hi = row["lo"], row["hi"]
    length = meta.get("length") or (len(value) if isinstance(value, tuple) else None)
    if name.endswith("_cov"):
        kind = "sigma3"
        unit = {"(rad/s)²": "deg/s", "(m/s²)²": "m/s²", "µT²": "µT"}.get(row["unit"], unit)
        scale = 180.0 / math.pi if unit == "deg/s" else 1.0
    elif isinstance(value, bool):
        kind = "bool"
    elif row["choices"]:
        kind = "choice"
    elif length == 3 and row["unit"] == "rad/s" and scale == 1.0:
        kind = "optvec" if meta.get("optional") else "vector"
        scale, unit = 180.0 / math.pi, "deg/s"      # a gyroscope bias reads in deg/s
    elif length == 3:
        kind = "optvec" if meta.get("optional") else "vector"
    elif length == 2:
        kind = "band2"
    elif isinstance(value, int) and row.get("integer"):
        kind = "int"
    elif isinstance(value, (int, float)) and row["log"]:
        kind = "log"
    elif (isinstance(value, (int, float)) and lo is not None and hi is not None
          and (hi - lo) * scale <= 10):
        kind = "linear"          # a short range in the shown unit: a slider
    elif isinstance(value, (int, float)):
        kind = "number"
    else:
        return None
    c = Control(est_name, name, None, kind, scale, unit, lo, hi)
    hint = hint_text({**row, "user_unit": unit}, kind)
    label = c.label()
    if kind == "bool":
        c.handle = gui.add_checkbox(label, value, hint=hint, order=order)
    elif kind == "choice":
        c.handle = gui.add_dropdown(label, tuple(row["choices"]), initial_value=value, hint=hint,
                                    order=order)
    elif kind in ("vector", "optvec", "sigma3"):
        v = c.to_gui(value)
        c.handle = gui.add_vector3(label, v, step=10.0 ** -precision_for(max(map(abs, v)) or 1.0),
                                   hint=hint, order=order)
    elif kind == "band2":
        c.handle = gui.add_vector2(label, c.to_gui(value), step=0.1, hint=hint, order=order)
    elif kind == "int":
        # no min/max given to viser: its box clamps silently (500 became 200); checked here
        c.handle = gui.add_number(label, int(value), step=1, hint=hint, order=order)
    elif kind == "linear":
        a, b = nice_ends(lo * scale, hi * scale)
        step = nice_step(b - a)
        v = min(max(c.to_gui(value), a), b)
        c.handle = gui.add_slider(label, a, b, step, v, marks=((a, fmt(a)), (b, fmt(b))),
                                  hint=hint, order=order)
    else:  # log and number: the value itself, in its unit; no min/max given to viser: its
        # box clamps a value typed outside them silently, on leaving it (100 in a box whose
        # maximum is 91.7 became 91.7); the range is checked here and a refusal says it
        v = c.to_gui(value)
        c.handle = gui.add_number(label, v, step=10.0 ** -precision_for(v), hint=hint, order=order)
    if kind in ("log", "number", "vector", "optvec", "sigma3"):
        show_value(c, value, force=True)       # viser sized it for every digit: show SIG
    # what this code set, of every kind: only a viewer's later update counts as typing
    c.shown_at = float(getattr(c.handle, "update_timestamp", 0.0) or 0.0)
    return c


# Decimals a number box takes. viser's box cuts what is typed to its ``precision`` (0.001
# typed in a box showing 5.73 arrived as 0, refused; 0.05 in a gate showing 10 arrived as 0,
# the gate off). The value set in it is rounded to SIG digits (Control.shown): it shows no more.
BOX_DECIMALS = 8


def show_value(c: Control, value, force: bool = False) -> None:
    """Set the control to ``value`` (SI), as :meth:`Control.shown` gives it; the arrows
    step by the value's last digit shown."""
    v = c.to_gui(value)
    if c.kind in ("log", "number"):
        p, step = BOX_DECIMALS, 10.0 ** -precision_for(v)
        if force or c.handle.precision != p or c.handle.step != step:
            c.handle.precision = p
            c.handle.step = step
    elif c.kind in ("vector", "optvec", "sigma3"):
        p, step = BOX_DECIMALS, 10.0 ** -precision_for(max(map(abs, v)) or 1.0)
        if force or c.handle.precision != p or c.handle.step != step:
            c.handle.precision = p
            c.handle.step = step
    c.handle.value = c.shown(value)
    c.shown_at = float(getattr(c.handle, "update_timestamp", 0.0) or 0.0)
