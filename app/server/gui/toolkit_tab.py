"""The page's "Lab" tab: record, calibrate, magnetometer calibration, replay, what-if
(its own panel, :mod:`app.server.gui.whatif_panel`), variants and disturbances (the same
operations as the API, on the toolkit's services: :class:`app.server.toolkit.Toolkit`).

The heading plot (every estimator's heading over the last 30 s, the injected disturbance
beside it) is what a viewer would pay most for: viser resends a chart whole, and the
server cannot know whether a browser shows the Lab tab (the tab choice stays in the
browser). So it is sent only while it has something to show (:meth:`ToolkitTab.monitor_live`:
a variant on the ensemble, a disturbance in its window, or "Live heading plot" ticked),
at most :data:`MONITOR_DRAW_HZ` times a second with :data:`MONITOR_POINTS` rows; at
the default view it sends nothing.

viser runs the callbacks on its own threads: each one hands its work to the server's
event loop (``run_coroutine_threadsafe``), where the toolkit lives; a refused
request comes back as a notification in the tab that clicked. :func:`run_toolkit_tab`
refreshes the read-outs and plots a few times a second.
"""

from __future__ import annotations

import asyncio
import html
import logging
import math
import time
from typing import Any, Callable

import numpy as np

from app.estimators import REASON_TEXT
from app.quaternion import not_estimated, q2euler_many
from app.live.changes import Change, PatchError, Variant
from app.server.gui.plots import send_data, unwrap_deg
from app.server.gui.scene import set_wxyz
from app.server.gui.whatif_panel import WhatIfPanel
from app.server.engine import EngineBusy
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError
from app.toolkit.inject import InjectionService

log = logging.getLogger("orientlab.toolkit_tab")

COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf")
AXIS_COLORS = ("#d62728", "#2ca02c", "#1f77b4")
MONITOR_S = 30.0
MONITOR_HZ = 50.0
MONITOR_DRAW_HZ = 2.0     # the heading plot's refreshes per second, while live
MONITOR_POINTS = 300      # rows sent per refresh (about the chart's width in pixels)
VARIANT_SLOTS = 3


class Monitor:
    """Heading of every estimator over the last :data:`MONITOR_S` s, with the injected
    disturbance's size beside it (fed from the core's record hook; ``injection``: the
    disturbances' marks and sizes, None: none)."""

    def __init__(self, core, injection: InjectionService | None = None):
        self.injection = injection
        self.t: list[float] = []
        self.yaw: dict[str, list[float]] = {}
        self._last_t = -math.inf
        self._session = None
        core.record_listeners.append(self._on_records)

    def _on_records(self, session, rec) -> None:
        if session is not self._session:    # a new stream (a new clock): start afresh
            self._session = session
            self.t.clear()
            self.yaw.clear()
            self._last_t = -math.inf
        if not len(rec):
            return
        keep = rec.t >= self._last_t + 1.0 / MONITOR_HZ
        if not keep.any():
            return
        idx = np.flatnonzero(keep)
        # at most MONITOR_HZ rows: thin out within the chunk
        sel, last = [], self._last_t
        for i in idx.tolist():
            if rec.t[i] >= last + 1.0 / MONITOR_HZ:
                sel.append(i)
                last = rec.t[i]
        self._last_t = last
        n0 = len(self.t)
        self.t.extend(rec.t[sel].tolist())
        # every instance's rows in one compiled call (the same conversion row by row)
        names = list(rec.q)
        if names:
            qs = np.stack([rec.q[n][sel] for n in names])          # (instances, rows, 4)
            yaw = np.degrees(q2euler_many(qs.reshape(-1, 4))[:, 0]).reshape(len(names), -1)
            yaw[not_estimated(qs)] = np.nan     # before its alignment: a gap
            for name, y in zip(names, yaw.tolist()):
                self.yaw.setdefault(name, [math.nan] * n0).extend(y)
        for name, col in self.yaw.items():
            if len(col) < len(self.t):
                col.extend([math.nan] * (len(self.t) - len(col)))
        cut = 0
        while cut < len(self.t) and self.t[cut] < self.t[-1] - MONITOR_S:
            cut += 1
        if cut:
            del self.t[:cut]
            for col in self.yaw.values():
                del col[:cut]

    def injected(self, t: np.ndarray) -> np.ndarray:
        """Size of the injected disturbance at times ``t`` (µT or m/s²), from the marks."""
        out = np.zeros_like(t)
        if self.injection is None:
            return out
        size = self.injection.size
        starts = {}
        for m in self.injection.marks:
            if m["event"] == "start":
                starts[m["id"]] = m
            elif m["event"] == "end" and m["id"] in starts:
                s = starts.pop(m["id"])
                out[(t >= s["t"]) & (t <= m["t"])] += size(m["id"])
        for i, s in starts.items():
            out[t >= s["t"]] += size(i)
        return out


GHOST_COLORS = ((220, 40, 40), (140, 70, 200), (30, 160, 200), (200, 160, 20), (90, 90, 90))


class VariantGhosts:
    """Each variant drawn as its own translucent phone with its name, beside the primary
    (the scene's own ghosts are the phone's estimate and the truth). Follows the ensemble:
    a variant added or removed appears or goes at the next scene refresh."""

    def __init__(self, server, tk: Toolkit):
        self.server = server
        self.core = tk.engine.core
        self.frames: dict[str, Any] = {}
        tk.engine.listeners.append(self.draw)

    def draw(self, _snapshot=None) -> None:
        b = self.core.ensemble
        variants = [n for n in b.names if b.base_of(n) != n]
        for name in list(self.frames):
            if name not in variants:
                self.frames.pop(name).remove()
        sc = self.server.scene
        for i, name in enumerate(variants):
            f = self.frames.get(name)
            if f is None:
                from app.server.gui.scene import phone_body
                f = sc.add_frame(f"/variant_{name}", show_axes=False)
                phone_body(sc, f"/variant_{name}", GHOST_COLORS[i % len(GHOST_COLORS)], opacity=0.3)
                sc.add_label(f"/variant_{name}/label", name, position=(0.0, -0.95, 0.0),
                             anchor="center-center")
                self.frames[name] = f
            est = b.estimator(name)
            if est.initialized:
                set_wxyz(f, est.q)


def scale_markdown(out: dict) -> str:
    """A gyroscope scale fit (``GyroScaleService``'s JSON) as short lines that fit the panel."""
    lines = [f"**{a}**: {s * 100:+.3f} % ± {sd * 100:.3f} %" + ("" if m else " (not measured)")
             for a, s, sd, m in zip("xyz", out["scale"], out["std"], out["measured"])]
    lines.append(f"{out['spans']} spans between rests; tilt at the rests {out['rms_before_deg']:.2f}° "
                 f"→ {out['rms_after_deg']:.2f}° with the fit")
    lines += [f"*{w}*" for w in out["warnings"]]
    return "  \n".join(lines)


def injections_html(active: list[str], cap: int) -> str:
    """The disturbances on now, in a box of fixed height (three lines; more scroll inside it):
    the Lab tab's controls below it stay where they are as disturbances start and end."""
    text = (f"active ({len(active)} of at most {cap}): " + "; ".join(active)) if active \
        else f"no disturbance active (at most {cap} at once)"
    return ("<div style='height:4em;overflow-y:auto;padding:2px 10px;font-size:0.9em;line-height:1.33'>"
            f"{html.escape(text)}</div>")


class ToolkitTab:
    """Builds the "Lab" tab in ``tabs`` (a viser tab group) of the shared GUI, on the
    toolkit ``tk``; ``server``: the viser server whose 3D scene the variants' ghosts
    join (None: no ghosts)."""

    def __init__(self, gui, tabs, tk: Toolkit, loop: asyncio.AbstractEventLoop, server=None):
        self.gui = gui
        self.tk = tk
        self.core = tk.engine.core
        self.loop = loop
        self.monitor = Monitor(self.core, tk.injection)
        self.ghosts = VariantGhosts(server, tk) if server is not None else None
        self._cal_shown = None
        self._scale_shown: dict[str, Any] | None = None   # the gyroscope-scale fit on the page
        self._known_recordings: tuple = ()
        self._monitor_due = 0.0           # loop time of the heading plot's next refresh
        self.monitor_sent = 0             # heading plot refreshes sent (tests, benchmarks)
        with tabs.add_tab("Lab"):
            self._build()

    # ----------------------------------------------------------------- building
    def _build(self) -> None:
        gui = self.gui
        self.dist_folder = gui.add_folder("Disturb (virtual magnet, shake)", expand_by_default=True)
        with self.dist_folder:
            self.mag_strength = gui.add_slider("Magnet [µT]", 5.0, 200.0, 5.0, 50.0,
                                               hint="strength of the magnet's field at the phone")
            self.mag_seconds = gui.add_slider("Magnet for [s]", 1.0, 30.0, 1.0, 5.0)
            self.mag_frame = gui.add_dropdown("Magnet fixed in", ("world", "sensor"),
                                              initial_value="world",
                                              hint="world: on the desk (turns with the phone in its "
                                                   "readings); sensor: stuck on the phone")
            self.mag_dir = gui.add_dropdown("Direction", ("east", "north", "up", "down", "x", "y", "z"),
                                            initial_value="east")
            b = gui.add_button("Bring a magnet", color="red",
                               hint="POST /api/inject {kind: magnet}")
            b.on_click(lambda ev: self._do(ev, lambda: self.tk.injection.inject({
                "kind": "magnet", "strength_uT": float(self.mag_strength.value),
                "seconds": float(self.mag_seconds.value), "frame": self.mag_frame.value,
                "direction": self.mag_dir.value}), "Magnet"))
            self.shake_amp = gui.add_slider("Shake [m/s²]", 1.0, 30.0, 1.0, 8.0)
            self.shake_seconds = gui.add_slider("Shake for [s]", 1.0, 30.0, 1.0, 3.0)
            s = gui.add_button("Shake", color="orange", hint="POST /api/inject {kind: shake}")
            s.on_click(lambda ev: self._do(ev, lambda: self.tk.injection.inject({
                "kind": "shake", "amplitude_ms2": float(self.shake_amp.value),
                "seconds": float(self.shake_seconds.value)}), "Shake"))
            nr = gui.add_button("Add the primary without rejection",
                                hint="a variant of the primary with every gate off, beside it")
            nr.on_click(lambda ev: self._add_variant(ev, "no-rejection"))
            self.inject_status = gui.add_html(injections_html([], self.tk.injection.max_active))
            self.monitor_follow = gui.add_checkbox(
                "Live heading plot", False,
                hint="Keep the heading plot below following the stream. Without it the plot "
                     "follows only while a variant runs or a disturbance is in its 30 s "
                     "window (each viewer pays for every refresh of a chart).")
            # fixed series (the page's uPlot keeps the count it was made with): the
            # builtins, VARIANT_SLOTS variants in the order they were added, the disturbance
            self._mon_builtins = [n for n in self.core.ensemble.names]
            self.p_monitor = self._plot("Heading [deg] of each estimator; injected size (grey)",
                                        self._mon_builtins + [f"variant {i + 1}" for i in range(VARIANT_SLOTS)]
                                        + ["disturbance"], height=220, x_range=(-MONITOR_S, 0.0))
        with gui.add_folder("Record", expand_by_default=False):
            self.rec_name = gui.add_text("Recording name", "", hint="empty: orientlab_<date>")
            rb = gui.add_button("Record", color="red")
            rb.on_click(lambda ev: self._do(ev, lambda: self.tk.recording.start(
                self.rec_name.value.strip() or None), "Recording"))
            sb = gui.add_button("Stop recording")
            sb.on_click(lambda ev: self._do(ev, self.tk.recording.stop, "Recording stopped"))
            self.rec_md = gui.add_markdown("")
        with gui.add_folder("Calibrate (keep the phone still)", expand_by_default=False):
            self.cal_seconds = gui.add_slider("Seconds", 2.0, 60.0, 1.0, 10.0)
            cb = gui.add_button("Start calibration", hint="POST /api/calibrate {seconds}")
            cb.on_click(self._start_calibration)
            self.cal_bar = gui.add_progress_bar(0.0, visible=False)
            self.cal_md = gui.add_markdown("")
            self.cal_sensor = gui.add_dropdown("Show sensor", ("acc", "gyr", "mag"), initial_value="acc")
            self.cal_sensor.on_update(lambda ev: self._call(self._draw_calibration, True))
            self.p_hist = [self._plot(f"{a} histogram and fitted Gaussian", ["count", "Gaussian"],
                                      height=140, x_label="value") for a in "xyz"]
            self.p_cal_t = self._plot("samples over time", ["x", "y", "z"], height=140)
            ab = gui.add_button("Apply to the estimators",
                                hint="noise levels, gyroscope bias, g0, m0 (formula 7)")
            ab.on_click(lambda ev: self._call(self._apply_calibration, ev))
            # shown only when the calibration does not look stationary: applying it
            # anyway is a separate, explicit choice (POST /api/calibrate/apply {force})
            self.cal_force = gui.add_button("Apply anyway (the phone moved)", color="orange",
                                            visible=False,
                                            hint="the bias and noise of a phone that moved "
                                                 "mislead the filters: only if you know why")
            self.cal_force.on_click(lambda ev: self._call(self._apply_calibration, ev, True))
            self.cal_preset = gui.add_text("Preset name", "calibrated")
            spb = gui.add_button("Save as preset")
            spb.on_click(lambda ev: self._do(ev, self._save_calibration_preset, "Preset saved"))
        with gui.add_folder("Magnetometer calibration", expand_by_default=False):
            gui.add_markdown("Turn the phone slowly in all directions while it collects.")
            self.mc_seconds = gui.add_slider("Seconds", 5.0, 120.0, 5.0, 30.0)
            mb = gui.add_button("Start collecting", hint="POST /api/magcal {seconds}")
            mb.on_click(lambda ev: self._do(ev, lambda: self.tk.magcal.start(
                float(self.mc_seconds.value)), "Turn the phone"))
            self.mc_bar = gui.add_progress_bar(0.0)
            self.mc_md = gui.add_markdown("")
            mab = self.mc_apply = gui.add_button("Apply the fit", disabled=True,
                                                 hint="only a fit that was not refused")
            mab.on_click(lambda ev: self._do(ev, lambda: self.tk.magcal.apply(False), "Applied"))
            mcb = gui.add_button("Clear (no correction)")
            mcb.on_click(lambda ev: self._do(ev, lambda: self.tk.magcal.apply(True), "Cleared"))
        with gui.add_folder("Gyroscope scale (from a recording)", expand_by_default=False):
            gui.add_markdown("Record: the phone still for 2 s, whole turns one way about one of its "
                             "axes while that axis is level, still again; each axis, both ways. "
                             "Then measure the recording (`orientlab gyro-scale`).")
            self.gs_name = gui.add_dropdown("Turns recording", ("(none)",))
            gb = gui.add_button("Measure the scale", hint="POST /api/gyro-scale {recordings: [name]}")
            gb.on_click(self._measure_scale)
            self.gs_md = gui.add_markdown("")
            self.gs_apply = gui.add_button("Apply gyr_scale to the estimators", disabled=True,
                                           hint="POST /api/gyro-scale/apply (the measured axes)")
            self.gs_apply.on_click(lambda ev: self._call(self._apply_scale, ev))
        with gui.add_folder("Replay", expand_by_default=False):
            self.rp_name = gui.add_dropdown("Recording", ("(none)",))
            pb = gui.add_button("Replay it")
            pb.on_click(lambda ev: self._replay(ev, {"name": self.rp_name.value}))
            self.rp_pause = gui.add_button("Pause / play")
            self.rp_pause.on_click(lambda ev: self._replay(
                ev, {"paused": not (self.tk.replay.control.paused if self.tk.replay.control else False)}))
            self.rp_speed = gui.add_slider("Speed [x]", 0.1, 10.0, 0.1, 1.0)
            self.rp_speed.on_update(lambda ev: ev.client is not None and self._replay(
                ev, {"speed": float(self.rp_speed.value)}))
            self.rp_seek = gui.add_slider("Seek [s]", 0.0, 1.0, 0.1, 0.0,
                                          hint="every estimator restarts cleanly at a seek")
            self.rp_seek.on_update(lambda ev: ev.client is not None and self._seek(ev))
            self.rp_loop = gui.add_checkbox("Loop", True)
            self.rp_loop.on_update(lambda ev: ev.client is not None and self._replay(
                ev, {"loop": bool(self.rp_loop.value)}))
            db = gui.add_button("Back to the demo")
            db.on_click(lambda ev: self._replay(ev, {"stop": True}))
            self.rp_md = gui.add_markdown("")
            self._seek_moved = 0.0                  # when a viewer last moved the seek slider
            self._rp_key: tuple | None = None        # (replay, restarts) the slider last showed
        with gui.add_folder("What-if (re-run a recording)", expand_by_default=False):
            self.whatif = WhatIfPanel(gui, self.tk, self._call, self._notify, self._plot)
        with gui.add_folder("Variants", expand_by_default=False):
            v1 = gui.add_button("Add lab-approx (2k beside 2j)",
                                hint="exercise 9: the approximate time update beside the exact one")
            v1.on_click(lambda ev: self._add_variant(ev, "lab-approx"))
            self.var_remove = gui.add_dropdown("Variant", ("(none)",))
            rm = gui.add_button("Remove variant")
            rm.on_click(self._remove_variant)
            self.var_md = gui.add_markdown("")

    def _plot(self, title: str, labels: list[str], height: int = 160, x_label: str = "t [s]",
              x_range: tuple[float, float] | None = None):
        series = ({"label": x_label},) + tuple(
            {"label": lab, "stroke": COLORS[i % len(COLORS)], "width": 1.5} for i, lab in enumerate(labels))
        z = (np.zeros(2),) * len(series)
        xs = {"time": False} if x_range is None else {"time": False, "auto": False, "range": list(x_range)}
        return self.gui.add_uplot(data=z, series=series, title=title,
                                  scales={"x": xs}, height=height, aspect=2.0)

    # ----------------------------------------------------------------- callbacks
    def _call(self, fn: Callable, *args) -> None:
        """Run ``fn(*args)`` on the event loop (from viser's thread)."""
        self.loop.call_soon_threadsafe(lambda: self._guard(fn, *args))

    def _guard(self, fn, *args) -> None:
        try:
            r = fn(*args)
            if asyncio.iscoroutine(r):
                asyncio.ensure_future(r)
        except Exception:
            log.exception("lab GUI action failed")

    def _notify(self, ev, title: str, body: str, color: str = "red") -> None:
        client = getattr(ev, "client", None)
        if client is not None:
            try:
                client.add_notification(title, body[:400], color=color, auto_close_seconds=6.0)
            except Exception:
                log.exception("notification failed")
        else:
            log.info("%s: %s", title, body)

    def _save_calibration_preset(self) -> str:
        """The calibration's preset, through the one preset save path; a refusal (a
        shipped name, the cap, a folder that refuses the write) as a ToolError."""
        return str(self.tk.save_preset(self.cal_preset.value.strip()))

    def _do(self, ev, fn: Callable, title: str) -> None:
        """Run a synchronous toolkit call on the loop; notify its outcome."""
        def run():
            try:
                out = fn()
            except ToolError as e:
                self._notify(ev, f"{title}: refused", f"{e.field}: {e.reason}")
                return
            text = out.get("text") or out.get("name") or "" if isinstance(out, dict) else str(out)
            self._notify(ev, title, str(text), color="green")
            self.refresh()
        self._call(run)

    def _seek(self, ev) -> None:
        self._seek_moved = time.monotonic()     # the refresh leaves the slider to the user a while
        self._replay(ev, {"seek_s": float(self.rp_seek.value)})

    def _replay(self, ev, body: dict) -> None:
        rs = self.tk.replay

        def run():
            try:
                if body.get("stop"):
                    rs.stop()
                    return
                if "name" in body:
                    rs.start(body["name"])
                    if rs.control is not None:
                        self.rp_seek.max = max(0.1, round(rs.control.duration_s, 1))
                    return
                if rs.control is None:
                    raise ToolError("name", "nothing is replayed: pick a recording and press Replay it")
                rs.set(**body)
            except ToolError as e:
                self._notify(ev, "Replay", f"{e.field}: {e.reason}")
        self._call(run)

    def _add_variant(self, ev, preset: str) -> None:
        async def run():
            try:
                name, base, params = self.tk.variants.preset(preset)
                checked = self.tk.variants.check_add(name, base, params)
                change = Change(add=[Variant(name, base, checked)])
            except ToolError as e:
                self._notify(ev, "Variant", f"{e.field}: {e.reason}")
                return
            await self._post(ev, change, f"{name} added")
        self._call(run)

    def _remove_variant(self, ev) -> None:
        async def run():
            try:
                change = Change(remove=[self.tk.variants.check_remove(self.var_remove.value)])
            except ToolError as e:
                self._notify(ev, "Variant", e.reason)
                return
            await self._post(ev, change, f"{self.var_remove.value} removed")
        self._call(run)

    async def _post(self, ev, change, ok_text: str, color: str = "green") -> bool:
        """Post a validated change to the filter task and say how it went: True once applied."""
        try:
            await self.tk.engine.apply(change, 5.0)
        except (PatchError, EngineBusy) as e:
            self._notify(ev, "Refused", str(e))
            return False
        self._notify(ev, "Done", ok_text, color=color)
        return True

    def _start_calibration(self, ev) -> None:
        async def run():
            try:
                await self.tk.calibration.calibrate(float(self.cal_seconds.value))
                self._notify(ev, "Calibration", "done: see the statistics", color="green")
                self._draw_calibration(True)
            except ToolError as e:
                self._notify(ev, "Calibration", e.reason)
        self._call(run)

    async def _apply_calibration(self, ev, force: bool = False) -> None:
        """"Apply to the estimators" (a calibration over a phone that moved is refused,
        with its reasons) or, ``force``, "Apply anyway (the phone moved)"."""
        checked = self._validated(ev, lambda: self.tk.calibration.change(force=force))
        if checked is None:
            return
        params, change = checked
        text = ("applied anyway: " if force else "calibration applied: ") + ", ".join(
            f"{n}: {', '.join(p)}" for n, p in params.items())
        if await self._post(ev, change, text, color="orange" if force else "green"):
            self.tk.calibration.note_applied()

    # ----------------------------------------------------------------- gyroscope scale
    def _measure_scale(self, ev) -> None:
        async def run():
            self.gs_md.content = f"measuring `{self.gs_name.value}`..."
            try:
                out = await self.tk.gyro_scale.fit_job([self.gs_name.value])
            except ToolError as e:
                self.gs_md.content = f"**not measured**: {e.reason}"
                self._notify(ev, "Gyroscope scale", e.reason)
                return
            self._show_scale(out)
            self._notify(ev, "Gyroscope scale", "measured: see the report", color="green")
        self._call(run)

    def _show_scale(self, out: dict[str, Any]) -> None:
        """The gyroscope-scale fit on the page, its apply button enabled if an axis was measured."""
        self._scale_shown = out
        self.gs_md.content = scale_markdown(out)
        self.gs_apply.disabled = not any(out["measured"])

    async def _apply_scale(self, ev) -> None:
        checked = self._validated(ev, self.tk.gyro_scale.change)
        if checked is not None:
            await self._post(ev, checked[1], "gyr_scale set: " + ", ".join(checked[0]))

    def _validated(self, ev, params_of: Callable[[], dict]):
        """A calibration's parameters and their validated change, or None (the refusal
        notified): nothing is applied unless all of it is valid."""
        try:
            params = params_of()
            return params, self.core.validate({"estimators": params})
        except ToolError as e:
            self._notify(ev, "Not applied", e.reason)
        except PatchError as e:
            self._notify(ev, "Not applied", str(e))
        return None

    def _draw_calibration(self, force: bool = False) -> None:
        res = self.tk.calibration.last
        if res is None or (res is self._cal_shown and not force):
            return
        self._cal_shown = res
        if self.cal_force.visible != (not res["stationary"]):
            self.cal_force.visible = not res["stationary"]
        name = self.cal_sensor.value
        s = res["sensors"].get(name)
        lines = [f"{res['n_rows']} rows over {res['duration_s']:.1f} s; "
                 + ("stationary" if res["stationary"] else "**not stationary**: " + "; ".join(res["warnings"]))]
        for sn, ss in res["sensors"].items():
            mean = ", ".join(f"{v:.4g}" for v in ss["mean"])
            std = ", ".join(f"{v:.3g}" for v in ss["std"])
            drift = ", ".join(f"{v:.3g}" for v in ss["drift_per_min"])
            normal = ", ".join("yes" if v else ("no" if v is not None else "n/a")
                               for v in ss["normality"]["normal_5pct"])
            if ss["unit"] == "rad/s":     # SI as the filters' covariances; the bias as Tuning shows it
                mean += " = " + ", ".join(f"{np.degrees(v):.3g}" for v in ss["mean"]) + " deg/s"
            lines.append(f"- **{ss['title']}** [{ss['unit']}]: mean ({mean}), σ ({std}), "
                         f"drift/min ({drift}), normal at 5 %: {normal}")
        if res.get("m0"):
            # rounded to what the sensors tell (g0 was printed with 16 digits)
            lines.append(f"- g0 = ({', '.join(f'{v:.2f}' for v in res.get('g0') or ())}) m/s², "
                         f"m0 (formula 7) = ({', '.join(f'{v:.1f}' for v in res['m0'])}) µT")
        self.cal_md.content = "\n".join(lines)
        if s is None:
            return
        for i, h in enumerate(s["histograms"]):
            c = np.array(h["centres"], float)
            self.p_hist[i].data = (c, np.array(h["counts"], float),
                                   np.array([np.nan if v is None else v for v in h["fit"]], float))
        ser = (res.get("series") or {}).get(name)
        if ser:
            self.p_cal_t.data = tuple(np.array([np.nan if v is None else v for v in ser[k]], float)
                                      for k in ("t", "x", "y", "z"))

    def refresh(self) -> None:
        """Read-outs and plots (on the event loop)."""
        tk = self.tk
        tk.tick()
        # recordings
        st = tk.recording.status()
        folder = tk.recording.folder        # every viewer sees this tab: no paths in it

        def size(n) -> str:
            n = float(n or 0)
            return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"

        def bare(text: str) -> str:
            for f in {str(folder.resolve()), str(folder)} - {".", "/", ""}:
                text = text.replace(f, folder.name or "recordings")
            return text
        if st["recording"]:
            seg = st["segments"][-1] if st["segments"] else {}
            lim = st.get("limits") or {}
            caps = [f"{lim['max_seconds'] / 60:g} min" if lim.get("max_seconds") else "",
                    size(lim["max_bytes"]) if lim.get("max_bytes") else ""]
            caps = [c for c in caps if c]
            self.rec_md.content = (
                f"**recording** `{seg.get('name', st['name'])}`: {st['seconds']:.1f} s, "
                f"{st['samples']} samples, {size(st.get('bytes'))} at "
                f"{size(st.get('bytes_per_s'))}/s" + (f" (stops at {' or '.join(caps)})" if caps else ""))
        else:
            last = st["last"]
            if last is None:
                self.rec_md.content = "not recording"
            elif last.get("empty"):
                self.rec_md.content = f"not recording; last: `{last['name']}` got no sample: nothing kept"
            else:
                why = last.get("error") or last.get("stop_reason")
                segs = last.get("segments") or []
                # a recording over several streams is one file per stream: name each, with
                # its own length (replaying the first name plays the first stream only)
                files = (", ".join(f"`{g['name']}` {g['seconds']:.1f} s" for g in segs)
                         if len(segs) > 1 else f"`{last['name']}` {last['seconds']:.1f} s")
                self.rec_md.content = bare(
                    f"not recording; last: {files}"
                    + (f" ({len(segs)} streams, {last['seconds']:.1f} s in all)" if len(segs) > 1 else "")
                    + f", {last['samples']} samples, {size(last.get('bytes'))}"
                    + (f" -- **stopped: {why}**" if why else ""))
        names = tuple(tk.recording.names()) or ("(none)",)
        if names != self._known_recordings:
            self._known_recordings = names
            for dd in (self.rp_name, self.gs_name):
                v = dd.value
                dd.options = names
                if v in names:
                    dd.value = v
        self.whatif.refresh(names)
        # calibration countdown
        cap = tk.calibration.capture
        if cap is not None and cap.result is None and cap.error is None:
            self.cal_bar.visible = True
            self.cal_bar.value = 100.0 * min(1.0, cap.elapsed / cap.seconds)
            self.cal_md.content = f"keep the phone still: {cap.remaining:.1f} s left"
        else:
            self.cal_bar.visible = False
            if cap is not None and cap.error:
                self.cal_md.content = f"**calibration failed**: {cap.error}"
            self._draw_calibration()
        # gyroscope scale: the last fit, measured here or through the API
        if tk.gyro_scale.last is not None and tk.gyro_scale.last is not self._scale_shown:
            self._show_scale(tk.gyro_scale.last)
        # magnetometer calibration
        ms = tk.magcal.status()
        c = ms.get("capture")
        if c is not None:
            self.mc_bar.value = 100.0 * c["coverage"]
            res = ms.get("result")
            refused = ms.get("refused")
            txt = [f"coverage {100 * c['coverage']:.0f} % of directions, {c['samples']} samples, "
                   f"{c['remaining_s']:.0f} s left"
                   + (f" -- **{c['error']}**" if c.get("error") and not refused else "")
                   + (f" ({c['note']})" if c.get("note") else "")]
            shown = res or (refused or {}).get("fit")
            if shown:
                txt.append(f"fit ({shown['model']}): offset ({', '.join(f'{v:.1f}' for v in shown['offset_uT'])}) µT, "
                           f"field {shown['field_uT']:.1f} µT; residual {shown['residual_before_uT']:.2f} -> "
                           f"{shown['residual_after_uT']:.2f} µT")
            if refused:     # shown with its reason, never applicable
                txt.append(f"**fit refused, not applicable**: {refused['reason']}")
            if self.mc_apply.disabled != (res is None):   # sent to every viewer: on change only
                self.mc_apply.disabled = res is None
            txt.append("applied: " + ("none" if ms["applied"] is None else "yes"))
            self.mc_md.content = "\n\n".join(txt)
        # replay
        rs = tk.replay.status()
        if rs["replaying"]:
            dur = max(0.1, round(rs["duration_s"], 1))
            if self.rp_seek.max != dur:     # a replay started by the API or --source too
                self.rp_seek.max = dur
            # the controls show the replay as it is (a new replay starts at 1x; the API may
            # change it): a value left from before would be taken for the state, and typing
            # it again changes nothing. Seek shows the playhead of a new replay, of a restart
            # at its end and of a paused one, unless just moved; not while it plays (the
            # status line below shows the playhead): set from here several times a second,
            # the box overwrote what a student was typing into it.
            if self.rp_speed.value != rs["speed"]:
                self.rp_speed.value = rs["speed"]
            if self.rp_loop.value != rs["loop"]:
                self.rp_loop.value = rs["loop"]
            pos = min(dur, round(rs["position_s"], 1))
            key = (rs["name"], rs["loops"])
            follow = rs["paused"] or key != self._rp_key
            self._rp_key = key
            if follow and abs(self.rp_seek.value - pos) >= 0.05 and time.monotonic() - self._seek_moved > 2.0:
                self.rp_seek.value = pos
            self.rp_md.content = (f"`{rs['name']}` {rs['position_s']:.1f} / {rs['duration_s']:.1f} s, "
                                  f"{rs['speed']:g}x" + (", **paused**" if rs["paused"] else "")
                                  + (", loop" if rs["loop"] else ""))
        else:
            self.rp_md.content = "not replaying"
        # variants
        b = self.core.ensemble
        variants = tuple(n for n in b.names if b.base_of(n) != n) or ("(none)",)
        old = tuple(self.var_remove.options)
        if old != variants:
            self.var_remove.options = variants
            added = [n for n in variants if n not in old and n != "(none)"]
            if added:   # the one just added is the one "Remove variant" ends (not an older one)
                self.var_remove.value = added[-1]
        self.var_md.content = self._readouts()
        # disturbances and the monitor
        act = tk.injection.injector.active
        cap = tk.injection.max_active
        self.inject_status.content = injections_html([a.d.describe() for a in act], cap)
        self._draw_monitor()

    def _readouts(self) -> str:
        """Every estimator's Euler angles, error to the phone and its last magnetometer
        decision: the variants' read-outs beside the builtins'."""
        from app.quaternion import angle_between
        b = self.core.ensemble
        phone = b.phone_q
        rows = ["| estimator | yaw pitch roll [deg] | to phone | magnetometer |", "|---|---|---|---|"]
        for n in b.names:
            if b.is_reference(n):
                continue
            est = b.estimator(n)
            e = np.degrees(q2euler_many(est.q[None, :])[0])
            err = "-" if phone is None else f"{math.degrees(angle_between(phone, est.q)):.1f}°"
            f = b.instances[n].flags("mag")
            dec = "-" if f is None else REASON_TEXT[f.mag]
            tag = "" if b.base_of(n) == n else f" ({b.base_of(n)} variant)"
            rows.append(f"| `{n}`{tag} | {e[0]:.1f} {e[1]:.1f} {e[2]:.1f} | {err} | {dec} |")
        return "\n".join(rows)

    def monitor_live(self) -> bool:
        """Whether the heading plot follows the stream: "Live heading plot" ticked, a
        variant on the ensemble, a disturbance active or one in the plot's window."""
        if self.monitor_follow.value or self.tk.injection.injector.active:
            return True
        b = self.core.ensemble
        if any(b.base_of(n) != n for n in b.names):
            return True
        m = self.monitor
        return bool(m.t) and any(mk["t"] >= m.t[-1] - MONITOR_S for mk in self.tk.injection.marks)

    def _draw_monitor(self) -> None:
        m = self.monitor
        if len(m.t) < 2 or not self.monitor_live():
            return
        now = self.loop.time()
        if now < self._monitor_due:
            return
        self._monitor_due = now + 1.0 / MONITOR_DRAW_HZ
        keep = np.unique(np.linspace(0, len(m.t) - 1, min(len(m.t), MONITOR_POINTS)).astype(np.int64))
        t = np.array(m.t)[keep]
        b = self.core.ensemble
        variants = [n for n in b.names if b.base_of(n) != n][:VARIANT_SLOTS]
        cols = []
        for n in self._mon_builtins + variants + [None] * (VARIANT_SLOTS - len(variants)):
            y = m.yaw.get(n) if n is not None else None
            cols.append(np.array(y, float)[keep] if y is not None and len(y) == len(m.t)
                        else np.full(len(t), np.nan))
        # one heading in every column: no comb at ±180°, no two estimators 360° apart
        cols = list(unwrap_deg(np.column_stack(cols), align=True).T)
        labels = self._mon_builtins + [variants[i] if i < len(variants) else f"variant {i + 1}"
                                       for i in range(VARIANT_SLOTS)]
        current = [s["label"] for s in self.p_monitor.series][1:-1]
        if current != labels:   # same number of series: only the names change
            n_b = len(self._mon_builtins)
            self.p_monitor.series = ({"label": "t [s]"},) + tuple(
                {"label": lab, "stroke": COLORS[i % len(COLORS)], "width": 1.5,
                 "show": i < n_b + len(variants)}
                for i, lab in enumerate(labels)) + (
                {"label": "disturbance", "stroke": "#999", "width": 1, "dash": [4, 4]},)
        # rows where an estimator had no value yet are gaps (null, never NaN: plots.py)
        send_data(self.p_monitor, (t - t[-1], *cols, m.injected(t)))
        self.monitor_sent += 1


async def run_toolkit_tab(g: ToolkitTab, hz: float = 2.0) -> None:
    """Refresh the Lab tab ``hz`` times a second."""
    while True:
        try:
            g.refresh()
        except Exception:
            log.exception("lab GUI refresh failed")
        await asyncio.sleep(1.0 / hz)
