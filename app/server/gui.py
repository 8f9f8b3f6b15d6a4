"""The viser GUI: live controls, read-outs and plots.

Controls are built from the estimators' parameter metadata
(:func:`app.params.describe`): a checkbox for a switch, a dropdown for choices, a
log-scale slider (labelled with the value in the user's unit) for a quantity tuned over
decades, a linear slider for a short range, a number field otherwise. Parameters
marked ``tunable=False`` (calibration matrices, references) are left to presets and
the API.

A control never touches the filter: its callback (on viser's threads) builds the same
PATCH body the HTTP API takes, validates it (:meth:`Engine.validate_patch`) and posts
it; the engine applies it before the next sample and then calls :meth:`Gui.sync`,
which sets every control from the estimators' parameters (the one source of truth).
Callbacks fired by that synchronisation are recognised and ignored, so nothing loops.
"""

from __future__ import annotations

import asyncio
import html
import logging
import math
import threading
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import numpy as np

from ..estimators import Reason, REJECTIONS
from ..params import describe, fields_of
from ..quaternion import q2euler_many
from .engine import H_LK, H_NIS_A, H_NIS_M, H_NORM, H_P, H_Q, H_T, Engine, PatchError
from .presets import list_presets, load_preset, save_preset
from .scene import Scene, describe_rejection

log = logging.getLogger("orientlab.gui")

SENSOR_SWITCHES = (("use_gyr", "Gyroscope"), ("use_acc", "Accelerometer"), ("use_mag", "Magnetometer"))
MAX_POINTS = 300          # per plot: 15 points/s over 20 s is smooth enough
EULER_COLORS = ("#d62728", "#2ca02c", "#1f77b4")


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def _nice_step(span: float) -> float:
    raw = span / 200.0
    e = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 5, 10):
        if raw <= m * e:
            return m * e
    return 10 * e


@dataclass
class Control:
    """One GUI control bound to one parameter of one estimator."""
    estimator: str
    name: str
    handle: Any
    kind: str                      # "bool", "choice", "log", "linear", "number"
    scale: float = 1.0             # user value = value * scale
    unit: str = ""

    def to_gui(self, value):
        if self.kind == "log":
            return math.log10(max(value * self.scale, 1e-300))
        if self.kind in ("linear", "number"):
            return value * self.scale
        return value

    def from_gui(self, v):
        if self.kind == "log":
            return 10.0 ** float(v) / self.scale
        if self.kind in ("linear", "number"):
            return float(v) / self.scale
        return v

    def same(self, a, b) -> bool:
        if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
            return math.isclose(a, b, rel_tol=1e-6 if self.kind == "log" else 1e-9, abs_tol=1e-12)
        return a == b

    def label(self, value) -> str:
        if self.kind == "log":
            return f"{self.name} = {_fmt(value * self.scale)} {self.unit}".rstrip()
        if self.kind in ("linear", "number") and self.unit:
            return f"{self.name} [{self.unit}]"
        return self.name


class Gui:
    """Builds the GUI on the shared ``server.gui`` (every browser sees the same)."""

    def __init__(self, server, engine: Engine, scene: Scene, settings):
        self.server = server
        self.engine = engine
        self.scene = scene
        self.settings = settings
        self._sync_thread: int | None = None
        self.controls: list[Control] = []
        gui = server.gui
        gui.configure_theme(show_share_button=False, control_width="large",
                            brand_color=(30, 90, 170),
                            titlebar_content=None)
        self.status = gui.add_html("", order=0)
        self.indicators = gui.add_html("", order=1)
        with gui.add_folder("Sensors", order=2):
            self.switches = {}
            for key, label in SENSOR_SWITCHES:
                h = gui.add_checkbox(label, self._common_value(key),
                                     hint=f"{key}: use the {label.lower()} in every estimator")
                h.on_update(self._make_switch_cb(key, h))
                self.switches[key] = h
            self.primary = gui.add_dropdown("Primary estimator", list(engine.estimators),
                                            initial_value=engine.primary,
                                            hint="the estimator drawn as the phone and plotted")
            self.primary.on_update(lambda ev: self._submit({"primary": self.primary.value}, ev))
            reset = gui.add_button("Reset filters", icon=None, hint="forget the orientation; align again")
            reset.on_click(lambda ev: self._submit({"reset": True}, ev))
            self.resume = gui.add_button("Resume demo", visible=settings.source != "none",
                                         hint="restart the demo / log replay after a phone has left")
            self.resume.on_click(lambda ev: engine.resume_background())
        self.readouts = gui.add_html("", order=3)
        tabs = gui.add_tab_group(order=4)
        with tabs.add_tab("Plots"):
            self._build_plots(gui)
        with tabs.add_tab("Tuning"):
            gui.add_markdown("Every change applies from the next sample. "
                             "Noise levels move over decades (log sliders).")
            for name, est in engine.estimators.items():
                with gui.add_folder(f"{name}: {type(est).title or type(est).__name__}",
                                    expand_by_default=(name == engine.primary)):
                    self._build_controls(gui, name, type(est.params))
        with tabs.add_tab("View"):
            for what, label, on in (("own", "Phone's own estimate (orange)", True),
                                    ("truth", "Ground truth (green, demo)", True),
                                    ("cones", "Uncertainty cones (2σ)", True),
                                    ("arrows", "Gravity and field arrows", True)):
                h = gui.add_checkbox(label, on)
                h.on_update(lambda ev, w=what, hh=h: scene.show(w, hh.value))
        with tabs.add_tab("Presets"):
            self.preset_name = gui.add_text("Preset name", "my-preset")
            load = gui.add_button("Load preset")
            save = gui.add_button("Save preset")
            self.preset_msg = gui.add_markdown(self._preset_list_md())
            load.on_click(self._on_load)
            save.on_click(self._on_save)
        engine.param_listeners.append(self.sync)

    # ------------------------------------------------------------------ controls
    def _common_value(self, key: str):
        return getattr(self.engine.params_of(self.engine.primary), key)

    def _build_controls(self, gui, est_name: str, params_cls) -> None:
        fmeta = fields_of(params_cls)
        current = self.engine.params_of(est_name)
        for row in describe(params_cls):
            name = row["name"]
            meta = fmeta[name].metadata
            if not meta.get("tunable", True) or name in dict(SENSOR_SWITCHES):
                continue
            value = getattr(current, name)
            scale, unit = float(row["user_scale"] or 1.0), row["user_unit"] or ""
            hint = f"{row['doc']} (API: {name}, in {row['unit'] or 'no unit'})"
            lo, hi = row["lo"], row["hi"]
            if isinstance(value, bool):
                c = Control(est_name, name, gui.add_checkbox(name, value, hint=hint), "bool")
            elif row["choices"]:
                c = Control(est_name, name, gui.add_dropdown(name, tuple(row["choices"]),
                                                             initial_value=value, hint=hint), "choice")
            elif isinstance(value, (int, float)) and row["log"] and lo and hi and lo > 0:
                c = Control(est_name, name, None, "log", scale, unit)
                a, b = math.log10(lo * scale), math.log10(hi * scale)
                marks = tuple((float(k), _fmt(10.0 ** k)) for k in range(math.ceil(a), math.floor(b) + 1))
                c.handle = gui.add_slider(c.label(value), a, b, 0.01, c.to_gui(value), marks=marks,
                                          hint=hint)
            elif isinstance(value, (int, float)) and lo is not None and hi is not None and hi - lo <= 10:
                c = Control(est_name, name, None, "linear", scale, unit)
                c.handle = gui.add_slider(c.label(value), lo * scale, hi * scale,
                                          _nice_step((hi - lo) * scale), c.to_gui(value), hint=hint)
            elif isinstance(value, (int, float)):
                c = Control(est_name, name, None, "number", scale, unit)
                c.handle = gui.add_number(c.label(value), c.to_gui(value),
                                          min=None if lo is None else lo * scale,
                                          max=None if hi is None else hi * scale, hint=hint)
            else:
                continue  # vectors and matrices: presets and the API only
            c.handle.on_update(self._make_param_cb(c))
            self.controls.append(c)

    def _ignored(self) -> bool:
        """True for callbacks fired by :meth:`sync` itself (same thread, during sync)."""
        return self._sync_thread == threading.get_ident()

    def _make_switch_cb(self, key: str, handle) -> Callable:
        def cb(ev):
            if self._ignored() or handle.value == self._common_value(key):
                return
            self._submit({key: bool(handle.value)}, ev)
        return cb

    def _make_param_cb(self, c: Control) -> Callable:
        def cb(ev):
            if self._ignored():
                return
            value = c.from_gui(c.handle.value)
            if c.same(value, getattr(self.engine.params_of(c.estimator), c.name)):
                return
            self._submit({"estimators": {c.estimator: {c.name: value}}}, ev)
        return cb

    def _submit(self, body: dict, ev=None) -> None:
        """Validate and post a change (the same body PATCH /api/params takes)."""
        try:
            change = self.engine.validate_patch(body)
        except PatchError as e:
            self._notify(ev, "Refused", str(e))
            self.engine.loop.call_soon_threadsafe(self.sync)
            return
        self.engine.post(change)

    def _notify(self, ev, title: str, body: str, color: str = "red") -> None:
        client = getattr(ev, "client", None)
        if client is not None:
            client.add_notification(title, body, color=color, auto_close_seconds=6.0)
        else:
            log.warning("%s: %s", title, body)

    def _on_load(self, ev) -> None:
        try:
            change = load_preset(self.engine, self.preset_name.value.strip())
        except PatchError as e:
            self._notify(ev, "Preset not loaded", e.reason)
            return
        self.engine.post(change)
        self._notify(ev, "Preset loaded", self.preset_name.value, color="green")

    def _on_save(self, ev) -> None:
        try:
            path = save_preset(self.engine, self.preset_name.value.strip())
        except (PatchError, OSError) as e:
            self._notify(ev, "Preset not saved", str(e))
            return
        self.preset_msg.content = self._preset_list_md()
        self._notify(ev, "Preset saved", str(path), color="green")

    def _preset_list_md(self) -> str:
        return "Presets: " + ", ".join(f"`{n}`" for n in list_presets(self.settings))

    def sync(self) -> None:
        """Set every control from the estimators' parameters (after a change)."""
        self._sync_thread = threading.get_ident()
        try:
            for key, h in self.switches.items():
                v = self._common_value(key)
                if h.value != v:
                    h.value = v
            if self.primary.value != self.engine.primary:
                self.primary.value = self.engine.primary
            for c in self.controls:
                value = getattr(self.engine.params_of(c.estimator), c.name)
                if not c.same(c.from_gui(c.handle.value), value):
                    c.handle.value = c.to_gui(value)
                if c.kind == "log":
                    lab = c.label(value)
                    if c.handle.label != lab:
                        c.handle.label = lab
        finally:
            self._sync_thread = None

    # ------------------------------------------------------------------ plots
    def _build_plots(self, gui) -> None:
        z = (np.zeros(2),)
        xs = {"x": {"time": False}}

        def series(*specs):
            return ({"label": "t [s]"},) + tuple(
                {"label": lab, "stroke": col, "width": 1.5, **({"dash": [6, 4]} if dash else {})}
                for lab, col, dash in specs)

        def plot(title, specs, height=170):
            s = series(*specs)
            return gui.add_uplot(data=z * len(s), series=s, title=title, scales=xs,
                                 height=height, aspect=2.0)

        self.p_euler = plot("Euler angles [deg] (solid ours, dashed phone)",
                            [(f"{n}", c, False) for n, c in zip(("yaw", "pitch", "roll"), EULER_COLORS)]
                            + [(f"phone {n}", c, True) for n, c in zip(("yaw", "pitch", "roll"), EULER_COLORS)],
                            height=200)
        self.p_err = plot("Error angle [deg]", [("to phone", "#ff7f0e", False),
                                               ("to truth", "#2ca02c", False)])
        self.p_acc = plot("|acc| [m/s²] and its gate band", [("|acc|", "#1f77b4", False),
                                                          ("band lo", "#888", True),
                                                          ("band hi", "#888", True)])
        self.p_mag = plot("|mag| and L_k [µT] and its band", [("|mag|", "#9467bd", False),
                                                            ("L_k", "#e377c2", False),
                                                            ("band lo", "#888", True),
                                                            ("band hi", "#888", True)])
        self.p_nis = plot("NIS and its gates", [("acc NIS", "#1f77b4", False),
                                               ("mag NIS", "#9467bd", False),
                                               ("acc gate", "#1f77b4", True),
                                               ("mag gate", "#9467bd", True)])

    def plot_steps(self) -> Iterator[None]:
        """Update the plots one by one, yielding after each (the caller may give the
        event loop a turn in between). They show the last ``history_s`` seconds, at most
        :data:`MAX_POINTS` points each, read once at the start (copies: the filter may
        run in between): O(MAX_POINTS) work, whatever the sample rate."""
        hist, span = self.engine.history, self.settings.history_s
        pose = hist.pose.window(span, MAX_POINTS)
        if pose.shape[0] < 2:
            return
        acc = hist.acc.window(span, MAX_POINTS)
        mag = hist.mag.window(span, MAX_POINTS)
        session = self.engine.session
        truth = session.truth if session is not None else None
        diag = self.engine.estimators[self.engine.primary].diagnostics()
        t_end = pose[-1, H_T]

        def const(x, v):
            return np.full(x.shape, np.nan if v is None else float(v))

        x = pose[:, H_T] - t_end
        q_ours, q_phone = pose[:, H_Q:H_Q + 4], pose[:, H_P:H_P + 4]
        has_p = np.isfinite(q_phone[:, 0])
        ours = np.degrees(q2euler_many(q_ours))
        phone = np.full_like(ours, np.nan)
        if np.any(has_p):
            phone[has_p] = np.degrees(q2euler_many(q_phone[has_p]))
        self.p_euler.data = (x, *ours.T, *phone.T)
        yield
        err_p = np.full(x.shape, np.nan)
        if np.any(has_p):
            err_p[has_p] = _angle_deg(q_ours[has_p], q_phone[has_p])
        err_t = np.full(x.shape, np.nan) if truth is None else \
            _angle_deg(q_ours, truth(pose[:, H_T] * 1000.0))
        self.p_err.data = (x, err_p, err_t)
        yield
        if acc.shape[0] > 1:
            band = diag.get("acc_band") or (None, None)
            x = acc[:, H_T] - t_end
            self.p_acc.data = (x, acc[:, H_NORM], const(x, band[0]), const(x, band[1]))
            yield
        if mag.shape[0] > 1:
            band = diag.get("mag_band") or (None, None)
            x = mag[:, H_T] - t_end
            self.p_mag.data = (x, mag[:, H_NORM], mag[:, H_LK], const(x, band[0]), const(x, band[1]))
            yield
        acc, mag = acc[-(MAX_POINTS // 2):], mag[-(MAX_POINTS // 2):]
        if acc.shape[0] + mag.shape[0] > 1:
            # acc and mag NIS on one time axis: each series NaN (a gap) at the other's times
            x = np.concatenate([acc[:, H_T], mag[:, H_T]])
            order = np.argsort(x, kind="stable")
            nis_a = np.concatenate([acc[:, H_NIS_A], np.full(mag.shape[0], np.nan)])[order]
            nis_m = np.concatenate([np.full(acc.shape[0], np.nan), mag[:, H_NIS_M]])[order]
            x = x[order] - t_end
            ga = diag.get("acc_nis_gate", diag.get("nis_gate"))
            gm = diag.get("mag_nis_gate", diag.get("nis_gate"))
            self.p_nis.data = (x, nis_a, nis_m, const(x, ga or None), const(x, gm or None))

    def refresh_plots(self) -> None:
        """Update every plot at once (see :meth:`plot_steps`)."""
        for _ in self.plot_steps():
            pass

    # ------------------------------------------------------------------ read-outs
    def refresh_text(self) -> None:
        eng = self.engine
        st = eng.state()
        src = html.escape(st["status"])
        t = "–" if st["t"] is None else f"{st['t']:.2f} s"
        self.status.content = (
            f"<div style='font-size:0.95em'><b>Source:</b> {src}<br><b>Phone time:</b> {t} "
            f"&nbsp; <b>Primary:</b> {html.escape(st['primary'])}</div>")
        self.indicators.content = _indicators_html(eng)
        self.readouts.content = _readouts_html(st)

    def refresh(self) -> None:
        self.refresh_text()
        self.refresh_plots()


def _angle_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Row-wise angle between two arrays of unit quaternions (deg): formula 2c."""
    return np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(qa * qb, 1)), 0, 1)))


def _pill(on: bool, text: str, color: str) -> str:
    bg = color if on else "#e6e6e6"
    fg = "#fff" if on else "#777"
    return (f"<span style='display:inline-block;margin:2px 4px 2px 0;padding:2px 8px;"
            f"border-radius:10px;background:{bg};color:{fg};font-size:0.9em'>{html.escape(text)}</span>")


def _indicators_html(eng: Engine) -> str:
    snap_flags = eng.last_flags[eng.primary]
    rest = snap_flags.get("rest")
    parts = [_pill(bool(rest and rest.rest), "standstill", "#2ca02c")]
    for sensor, title in (("acc", "acc disturbed"), ("mag", "mag disturbed")):
        f = snap_flags.get(sensor)
        on = f is not None and getattr(f, sensor) in REJECTIONS
        text = f"{title}: {describe_rejection(sensor, f)}" if on else title
        parts.append(_pill(on, text, "#d62728"))
    return "<div>" + "".join(parts) + "</div>"


def _deg3(v) -> str:
    return " ".join(f"{x:7.1f}°" for x in v) if v else "–"


def _readouts_html(st: dict) -> str:
    rates = ", ".join(f"{k} {v:.0f} Hz" for k, v in sorted(st["rates_hz"].items()) if v)
    c = st["counts"]
    upd = c["updates"].get(st["primary"], {})

    def used(sensor):
        d = upd.get(sensor, {})
        rej = sum(v for k, v in d.items() if Reason[k.upper()] in REJECTIONS)
        return f"{d.get('used', 0)} used, {rej} rejected"

    err = st["error_to_phone_deg"]
    err_t = st["error_to_truth_deg"]
    rows = [
        ("Euler yaw pitch roll", f"<code>{_deg3(st['euler_deg'])}</code>"),
        ("phone's own", f"<code>{_deg3(st['phone_euler_deg'])}</code>"),
        ("error to phone", "–" if err is None else f"{err:.2f}°"
         + ("" if err_t is None else f" &nbsp; (to truth {err_t:.2f}°)")),
        ("rates", rates or "–"),
        ("acc updates", used("acc")),
        ("mag updates", used("mag")),
        ("lines", f"{c.get('lines', 0)} ({c.get('malformed', 0)} malformed, "
                  f"{c.get('late', 0)} late)"),
    ]
    body = "".join(f"<tr><td style='color:#666;padding-right:8px'>{k}</td><td>{v}</td></tr>"
                   for k, v in rows)
    return f"<table style='font-size:0.9em'>{body}</table>"


async def run_gui(gui: Gui, hz: float) -> None:
    """Refresh the read-outs and plots at ``hz``, giving the event loop a turn between
    the read-outs and each plot: the filter task (and its latency) never waits for a
    whole refresh."""
    loop = asyncio.get_running_loop()
    period = 1.0 / hz
    due = loop.time()
    while True:
        try:
            gui.refresh_text()
            await asyncio.sleep(0)
            for _ in gui.plot_steps():
                await asyncio.sleep(0)
        except Exception:
            log.exception("GUI refresh failed")
        due = max(due + period, loop.time())      # a steady hz, no catching up after a stall
        await asyncio.sleep(due - loop.time())
