"""The viser GUI: live controls and read-outs (the plots are the landing page's).

Layout (at 1600x900 and 1280x720 the phone, the plots and the tuning controls are
visible at once): the plots in a panel of the landing page beside this viewer
(``static/plots.js``, fed by WS /ws/plots through :class:`app.server.gui.plots.PlotFeed`);
in the control panel the stream line (source, seconds since the stream started, primary), the indicators
(standstill, acc / mag disturbed with the gate and its value), the sensor switches,
then tabs: Tuning (one folder per estimator, the primary's first; open for a viewer that
connects while it is the primary: viser keeps an open viewer's folders as they are), Read-outs,
View, Presets (and Lab).

Controls are built from the estimators' parameter metadata (:mod:`app.server.gui.controls`):
every parameter of every estimator, in its user unit, with a hover text that says what
it is, its unit and what raising it does.

A control never touches the filter: its callback (on viser's threads) builds the same
PATCH body the HTTP API takes, validates it (:meth:`Engine.validate_patch`) and posts
it; the engine applies it before the next sample and then calls :meth:`Gui.sync`,
which sets every control from the estimators' parameters (the one source of truth).
Callbacks fired by that synchronisation are recognised and ignored, so nothing loops.

The indicators are computed once per refresh from one snapshot and drawn both as the
pills and as the 3D label (:meth:`Scene.set_indicators`): they show the same text.
A rejection lights its pill for at least :data:`HOLD_S` (a shake refuses some samples
and accepts others: a pill that followed each sample would flicker unseen).
"""

from __future__ import annotations

import asyncio
import html
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.estimators import AVERAGED_IN, Reason, is_rejected
from app.params import describe, fields_of
from app.server.gui.controls import Control, build_control, show_value
from app.live.ensemble import SENSORS
from app.server.engine import Engine, PatchError
from app.server.gui.plots import PlotFeed
from app.server.presets import (NAME_RE, list_presets, load_preset, load_preset_path, load_preset_text,
                      save_preset, save_preset_text, shipped_names)
from app.server.gui.scene import Indicators, Scene, describe_rejection
from app.toolkit.calibration import BIAS_ESTIMATORS, BIAS_MAX_S, BIAS_MIN_S, rest_bias, bias_change
from app.toolkit.errors import ToolError

log = logging.getLogger("orientlab.gui")

SENSOR_SWITCHES = (("use_gyr", "Gyroscope"), ("use_acc", "Accelerometer"), ("use_mag", "Magnetometer"))
HOLD_S = 1.0              # a rejection keeps its indicator lit this long
# a number box sends every keystroke: a refused value ("0" on the way to "0.5") is set back
# to the value in force, and said, only once the typing has paused this long (a loaded PC's
# browser, drawing the 3D view in software, took 1.5 s between two keys)
REFUSAL_SETTLE_S = 3.0
TYPING_S = 2.0            # a box typed in this recently is left alone by a sync (< REFUSAL_SETTLE_S)
PRESETS_REFRESH_S = 2.0   # the Presets tab lists the folder again this often (a listing of a few files)
CONTROL_PANEL_PX = 340    # the control panel, docked right of the 3D view


class Gui:
    """Builds the GUI on the shared ``server.gui`` (every browser sees the same)."""

    def __init__(self, server, engine: Engine, scene: Scene, settings):
        self.server = server
        self.engine = engine
        self.scene = scene
        self.settings = settings
        self._sync_thread: int | None = None
        self._refusal = None      # the pending set-back of a refused number (loop handle)
        self._settle = None       # the sync once the typing in a box pauses (loop handle)
        self.controls: list[Control] = []
        self.folders: dict[str, object] = {}
        self._hold: dict[str, tuple[str, float, float]] = {}  # sensor -> (text, lit until, since)
        self._rej_seen: dict[str, int] = {s: 0 for s in SENSORS}
        self._rej_primary = engine.core.ensemble.primary
        self.indicators_now = Indicators()
        gui = server.gui
        gui.configure_theme(show_share_button=False, control_width="large",
                            brand_color=(30, 90, 170), titlebar_content=None)
        # the control panel docked right: the 3D view is the rest of the frame (its
        # centre, where the phone is, not under the panel)
        if hasattr(gui, "main_panel"):
            panel = gui.main_panel
            panel.dock_right()
            panel.set_width(CONTROL_PANEL_PX)
        self.status = gui.add_html("", order=0)
        self.indicators = gui.add_html("", order=1)
        with gui.add_folder("Sensors and estimator", order=2):
            self.switches = {}
            for key, label in SENSOR_SWITCHES:
                h = gui.add_checkbox(label, self._common_value(key),
                                     hint=f"Use the {label.lower()} in every estimator (off: "
                                          f"the filters run without it, as in the lab's exercise). "
                                          f"API name: {key}.")
                h.on_update(self._make_switch_cb(key, h))
                self.switches[key] = h
            self.primary = gui.add_dropdown(
                "Primary estimator", engine.core.ensemble.names, initial_value=engine.core.ensemble.primary,
                hint="The estimator drawn as the phone, plotted and shown in the read-outs; "
                     "every estimator runs on every sample.")
            self.primary.on_update(self._on_primary)
            reset = gui.add_button("Reset filters", hint="Forget the orientation and align again "
                                                         "from the next samples.")
            reset.on_click(lambda ev: self._submit({"reset": True}, ev))
            # enabled only after a phone has left and the demo (or log replay) stays paused;
            # always there, greyed otherwise: appearing, it would push the tabs below it down
            # under the pointer just as the phone leaves
            self.resume = gui.add_button("Resume demo", disabled=True,
                                         hint="Restart the demo / log replay after a phone has "
                                              "left (greyed while a phone streams or nothing waits).")
            self.resume.on_click(lambda ev: engine.resume_background())
        # The plots are drawn by the landing page (static/plots.js, fed by WS /ws/plots:
        # only the new points, 20 times a second): a panel beside this viewer, so the 3D
        # view keeps its width for the phone. viser 1.1's charts take whole data only.
        # (kind, start_s, end_s) of the disturbances injected into a stream (the lab's
        # InjectionService.injected_spans, set in the lifespan): drawn over |acc| and |mag|
        self.injections: Callable[[Any], list[tuple[str, float, float]]] | None = None
        # whether a background source (the demo, a log replay) runs as a task now (set in the
        # lifespan, which owns the tasks): "Resume demo" resumes that task, and nothing else
        self.background: Callable[[], bool] = lambda: False
        self.feed = PlotFeed(engine.core, settings.history_s,
                             injections=lambda s: self.injections(s) if self.injections else [])
        engine.plot_feed = self.feed
        tabs = self.tabs = gui.add_tab_group(order=3)   # the Lab tab joins it (gui/toolkit_tab.py)
        with tabs.add_tab("Tuning"):
            gui.add_markdown("Every change applies from the next sample. Hover a control "
                             "for what it does. The primary estimator comes first.")
            self.bias_folder, self._bias_for = None, None   # lab's bias tool (_build_bias)
            self._build_bias(gui)
            for name in engine.core.ensemble.names:
                est = engine.core.ensemble.estimator(name)
                folder = gui.add_folder(f"{name}: {type(est).title or type(est).__name__}",
                                        expand_by_default=(name == engine.core.ensemble.primary),
                                        order=self._folder_order(name))
                self.folders[name] = folder
                with folder:
                    self._build_controls(gui, name, type(est.params))
        with tabs.add_tab("Read-outs"):
            self.readouts = gui.add_html("")
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
            # a preset file on this PC (e.g. from `orientlab calibrate`), or uploaded
            self.preset_file = gui.add_text("Preset file", "", hint="path of a .toml preset on "
                                            "this PC, e.g. written by orientlab calibrate")
            gui.add_button("Load file").on_click(self._on_load_path)
            gui.add_upload_button("Upload preset (.toml)", mime_type=".toml",
                                  hint="load a preset file from this browser's computer; it "
                                       "is also kept in the preset list").on_upload(self._on_upload)
        engine.param_listeners.append(self.sync)

    # ------------------------------------------------------------------ controls
    def _common_value(self, key: str):
        # viser's threads call this too: one schema of the ensemble, never the live one (a
        # variant removed meanwhile, the primary with it, cannot be half seen)
        schema = self.engine.core.ensemble.schema
        return getattr(schema.params_of(schema.primary), key)

    def _folder_order(self, name: str) -> float:
        names = self.engine.core.ensemble.names
        return 10.0 if name == self.engine.core.ensemble.primary else 11.0 + names.index(name)

    def _build_controls(self, gui, est_name: str, params_cls) -> None:
        fmeta = fields_of(params_cls)
        current = self.engine.core.ensemble.params_of(est_name)
        for row in describe(params_cls):
            name = row["name"]
            if name in dict(SENSOR_SWITCHES):
                continue          # the common switches above set every estimator
            c = build_control(gui, est_name, row, getattr(current, name), fmeta[name].metadata)
            if c is None:
                continue
            c.handle.on_update(self._make_param_cb(c))
            self.controls.append(c)

    def _build_bias(self, gui) -> None:
        """Give ``lab`` (which does not estimate it) the gyroscope bias: the mean rate of
        the last N s, when the phone lay still then."""
        have = [n for n in BIAS_ESTIMATORS if n in self.engine.core.ensemble.instances]
        if not have:
            return
        # just before lab's own folder: the primary's controls stay first (see sync())
        self._bias_for = have[0]
        self.bias_folder = gui.add_folder("Gyroscope bias for lab",
                                          order=self._folder_order(have[0]) - 0.5)
        with self.bias_folder:
            self.bias_seconds = gui.add_number(
                "Rest window [s]", 3.0, min=BIAS_MIN_S, max=BIAS_MAX_S, step=0.5,
                hint="How many of the last seconds of gyroscope samples to average. The phone "
                     "must lie still for that long (it checks).")
            self.bias_button = gui.add_button(
                "Calibrate gyro bias (last N s at rest)",
                hint="Average the gyroscope over the rest window and give it to lab as gyr_bias "
                     "(subtracted from every sample). Refused if the phone moved. "
                     "POST /api/calibrate/bias {seconds}")
            self.bias_button.on_click(self._on_calibrate_bias)

    def _on_calibrate_bias(self, ev) -> None:
        """POST /api/calibrate/bias from the page (the same checks and the same change),
        worked out on the loop, which owns the stream's history and the ensemble (this
        callback runs on viser's thread)."""
        seconds = float(self.bias_seconds.value)

        def on_loop() -> None:
            core = self.engine.core
            try:
                bias = rest_bias(core, seconds)
                params = bias_change(core, bias)
            except ToolError as e:
                self._notify(ev, "Bias not set", e.reason)
                return
            self._submit({"estimators": params}, ev)
            d = np.degrees(bias)
            self._notify(ev, "Gyroscope bias set", f"{', '.join(params)}: gyr_bias = "
                         f"({d[0]:.2f}, {d[1]:.2f}, {d[2]:.2f}) deg/s", color="green")
        self.engine.loop.call_soon_threadsafe(on_loop)

    def _on_primary(self, ev) -> None:
        """A viewer picked a primary. Not when :meth:`sync` set the menu (viser calls the
        callback for a value set from here too): posting that value back made two changes in
        flight swap the primary for ever, a change per sample in every recording."""
        if self._ignored() or ev.client is None or self.primary.value == self.engine.core.ensemble.primary:
            return
        self._submit({"primary": self.primary.value}, ev)

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
            typed = c.handle.value
            self.engine.loop.call_soon_threadsafe(self._typing)
            try:
                value = c.from_gui(typed)
            except (TypeError, ValueError):
                self._refuse_later(ev, f"estimators.{c.estimator}.{c.name}: not a number", c, typed)
                return
            info = self.engine.core.ensemble.schema.instances.get(c.estimator)
            if info is None:        # its variant was removed meanwhile (controls going too)
                return
            # no change: what the box shows for the value in force (a value typed to more
            # digits than it shows is a change: 0.2865 where 0.286 is shown)
            if c.holds(typed, getattr(info.params, c.name)):
                return
            why = c.out_of_range(value)
            if why is not None:          # set back, whatever the kind: no other field mends it
                self._refuse_later(ev, why, c, typed, keep=False)
                return
            self._submit({"estimators": {c.estimator: {c.name: value}}}, ev, typing=(c, typed))
        return cb

    def _typing(self) -> None:
        """A parameter control changed (on the loop): a set-back pending is off, and the
        controls are synced once the typing pauses (:meth:`sync` leaves a box alone while
        it is typed in: each key is applied a moment after the next is typed, and writing
        the value in force back then changed the number under the fingers)."""
        if self._refusal is not None:
            self._refusal.cancel()
            self._refusal = None
        if self._settle is not None:
            self._settle.cancel()
        # after a refusal's set-back, which says why (a sync first set the box back, and the
        # refusal, finding another value in it, was not said)
        self._settle = self.engine.loop.call_later(REFUSAL_SETTLE_S + 0.5, self.sync)

    def _refuse_later(self, ev, text: str, c: Control | None = None, typed=None,
                      keep: bool | None = None) -> None:
        """A control's refused value (on viser's thread): said and set back to the value in
        force once the typing pauses (:data:`REFUSAL_SETTLE_S`), not at once: a set-back
        between two keystrokes made "0.5" in a box holding 2 become "2.5". Not at all if
        the box holds another value by then (viser's threads may judge the "0" of "0.05"
        after the "0.05": its refusal was said after 0.05 was applied). A control of
        several fields (a band, three σ) keeps what was typed (``keep``, by default for those):
        a band or a covariance is valid only once every field is typed, one at a time; a
        number out of its range is set back (no other field mends it)."""
        loop = self.engine.loop
        multi = (c is not None and c.kind in Control.MULTI) if keep is None else keep

        def fire() -> None:
            self._refusal = None
            if c is not None and c.handle.value != typed:
                return          # typed on: this value is no longer in the box
            if multi:
                c.kept = typed      # left in the box: syncs leave it there while it is
                self._notify(ev, "Not applied yet", f"{text} (the value in force stays until "
                                                    "every field makes a valid one)", color="yellow")
                return
            self._notify(ev, "Refused", f"{text} (the value in force stays)")
            self.sync()

        def arm() -> None:
            self._typing()
            self._refusal = loop.call_later(REFUSAL_SETTLE_S, fire)
        loop.call_soon_threadsafe(arm)

    def _submit(self, body: dict, ev=None, typing: tuple | None = None) -> None:
        """Validate and post a change (the same body PATCH /api/params takes). Runs on
        viser's threads: validation reads one schema of the ensemble (thread-safe); the
        filter task refuses the change if its estimator went meanwhile (a variant
        removed), and that refusal comes back here as a notice. ``typing``: from a
        parameter's box, ``(control, value typed)``: its refusal waits for the typing to pause."""
        try:
            change = self.engine.core.validate(body)
        except PatchError as e:
            if typing:
                self._refuse_later(ev, str(e), *typing)
                return
            self._notify(ev, "Refused", str(e))
            self.engine.loop.call_soon_threadsafe(self.sync)
            return
        loop = self.engine.loop

        def post() -> None:     # on the loop: the future belongs to it
            done = loop.create_future()
            done.add_done_callback(lambda f: self._after_apply(f, ev))
            self.engine.post(change, done)
        loop.call_soon_threadsafe(post)

    def _after_apply(self, done, ev) -> None:
        """A posted change's outcome (on the loop): a refusal is shown, the controls
        set back to the parameters in force."""
        if done.cancelled() or done.exception() is None:
            return
        e = done.exception()
        self._notify(ev, "Refused", str(e) if isinstance(e, PatchError) else repr(e))
        self.sync()

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
        self._said_loaded(ev, change, self.preset_name.value)

    def _on_load_path(self, ev) -> None:
        try:
            change = load_preset_path(self.engine, self.preset_file.value)
        except PatchError as e:
            self._notify(ev, "Preset not loaded", e.reason)
            return
        self.engine.post(change)
        self._said_loaded(ev, change, self.preset_file.value[-80:])

    def _on_upload(self, ev) -> None:
        f = ev.target.value
        stem = Path(f.name).stem
        try:
            change = load_preset_text(self.engine, f.content, source=f.name[:80])
            if NAME_RE.fullmatch(stem) and stem not in shipped_names():
                save_preset_text(self.settings, stem, f.content)
                self.preset_msg.content = self._preset_list_md()
        except (PatchError, OSError) as e:
            self._notify(ev, "Preset not loaded", str(e)[:300])
            return
        self.engine.post(change)
        self._said_loaded(ev, change, f.name[:80])

    def _on_save(self, ev) -> None:
        try:
            path = save_preset(self.engine, self.preset_name.value.strip())
        except (PatchError, OSError) as e:
            self._notify(ev, "Preset not saved", str(e))
            return
        self.preset_msg.content = self._preset_list_md()
        self._notify(ev, "Preset saved", str(path), color="green")

    def _said_loaded(self, ev, change, what: str) -> None:
        """"Preset loaded", and what reading it said (a key read as its new name, a removed
        one left out): the teacher sees it here, not only in the terminal."""
        if change.notes:
            self._notify(ev, "Preset loaded, with changes", f"{what}: " + "; ".join(change.notes)[:600],
                         color="yellow")
        else:
            self._notify(ev, "Preset loaded", what, color="green")

    def refresh_presets(self) -> None:
        """The Presets tab's list, as the folder holds it now: presets saved through the
        API, by a calibration or dropped into the folder show without a save from here."""
        md = self._preset_list_md()
        if self.preset_msg.content != md:
            self.preset_msg.content = md

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
            ensemble = self.engine.core.ensemble
            if self.primary.value != ensemble.primary:
                self.primary.value = ensemble.primary
            for name, folder in self.folders.items():
                order = self._folder_order(name)
                if folder.order != order:
                    folder.order = order
                    if name == ensemble.primary:
                        folder.expand_by_default = True
            if self.bias_folder is not None:
                order = self._folder_order(self._bias_for) - 0.5
                if self.bias_folder.order != order:
                    self.bias_folder.order = order
            for c in self.controls:
                if c.typed_recently(TYPING_S):
                    continue            # being typed in (synced when the typing pauses)
                if c.kept is not None and c.handle.value == c.kept:
                    continue            # fields typed that are not a valid value yet: kept
                value = getattr(ensemble.params_of(c.estimator), c.name)
                if not c.gui_same(value):
                    show_value(c, value)
        finally:
            self._sync_thread = None

    # ------------------------------------------------------------------ plots
    def stream_t0(self) -> float | None:
        """The phone-clock time (s) of the stream's first motion sample."""
        return self.engine.core.t_first

    # ------------------------------------------------------------------ read-outs
    def indications(self) -> Indicators:
        """Standstill and the disturbances of the primary, from one snapshot; a rejection
        stays lit for :data:`HOLD_S` with the gate and value of the last refused sample."""
        eng = self.engine
        snap = eng.core.snapshot()
        now = time.monotonic()
        primary = snap.primary
        inst = eng.core.ensemble.instances[primary]
        if primary != self._rej_primary:
            self._rej_primary = primary
            self._hold.clear()
            self._rej_seen = {s: 0 for s in SENSORS}
        out = {}
        for sensor, flags in (("acc", snap.acc_flags), ("mag", snap.mag_flags)):
            n_rej = inst.rejections(sensor)
            seen = self._rej_seen[sensor]
            if n_rej < seen:              # the counts were reset (a new stream)
                self._hold.pop(sensor, None)
                seen = 0
            text = None
            if flags is not None and flags.rejected(sensor):
                text = describe_rejection(sensor, flags)
            elif n_rej > seen:            # refused since the last look, accepted again now
                last = inst.rejected_flags(sensor)
                text = describe_rejection(sensor, last) if last is not None else "refused by a gate"
            held = self._hold.get(sensor)
            if text is not None:
                if held is not None and held[1] > now and now - held[2] < HOLD_S:
                    # lit: keep the words for a while (the 3D label is drawn a frame or
                    # two after the pill; a value changing at 10 Hz would differ)
                    self._hold[sensor] = (held[0], now + HOLD_S, held[2])
                else:
                    self._hold[sensor] = (text, now + HOLD_S, now)
            self._rej_seen[sensor] = n_rej
            held = self._hold.get(sensor)
            out[sensor] = held[0] if held is not None and held[1] > now else None
        return Indicators(rest=snap.rest, acc=out["acc"], mag=out["mag"],
                          aligning=not snap.initialized and snap.t is not None,
                          waiting_for="waiting for the phone's ORI"
                          if eng.core.ensemble.is_reference(primary)
                          else "aligning…")

    def refresh_text(self, readouts: bool = True) -> None:
        """The indicators (pills and the 3D label); with ``readouts`` also the status
        line and the read-outs (from the API's state: the costlier part)."""
        ind = self.indications()
        self.indicators_now = ind
        # "Resume demo": only while a background source (demo, replay) waits, paused, and no
        # phone streams now
        waiting = (self.background() and self.engine.background_paused
                   and self.engine.core.source_kind() != "phone")
        if self.resume.disabled == waiting:
            self.resume.disabled = not waiting
        self.indicators.content = _indicators_html(ind)
        self.scene.set_indicators(ind)
        if not readouts:
            return
        eng = self.engine
        st = eng.state()
        src = html.escape(st["status"])
        t0 = self.stream_t0()
        t = "–" if st["t"] is None or t0 is None else f"{st['t'] - t0:.1f} s"
        self.status.content = _status_html(src, t, html.escape(st["primary"]), _error_text(st))
        self.readouts.content = _readouts_html(st)

    def refresh(self) -> None:
        self.refresh_text()


# The status and the indicators sit above the tabs: each line keeps its height whatever it
# says, so that a pill lighting up (a magnet brought, a shake) never moves the controls
# below under the pointer. A text too long for its line ends in "…" and is whole on hover.
_ONE_LINE = "white-space:nowrap;overflow:hidden;text-overflow:ellipsis;height:1.35em"
_TWO_LINES = ("display:-webkit-box;-webkit-box-orient:vertical;-webkit-line-clamp:2;"
              "overflow:hidden;height:2.7em")


def _status_html(src: str, t: str, primary: str, error: str) -> str:
    """The status block, always four lines: the source (two), the stream time and primary,
    the error. Each argument is HTML already (:func:`_error_text` for ``error``)."""
    return (f"<div style='font-size:0.92em;line-height:1.35'>"
            f"<div title='{src}' style='{_TWO_LINES}'><b>Source:</b> {src}</div>"
            f"<div style='{_ONE_LINE}'><b>Stream time:</b> {t} &nbsp; <b>Primary:</b> {primary}</div>"
            f"<div style='{_ONE_LINE}'><b>Error:</b> {error}</div></div>")


def _error_text(st: dict) -> str:
    parts = []
    if st["error_to_truth_deg"] is not None:
        parts.append(f"to truth {st['error_to_truth_deg']:.1f}°")
    if st["error_to_phone_deg"] is not None:
        # a difference, not an error: the phone's own estimate is itself degrees off
        parts.append(f"vs phone's own {st['error_to_phone_deg']:.1f}°")
    return ", ".join(parts) or "– (no reference in this stream)"


def _pill(on: bool, text: str, color: str) -> str:
    bg = color if on else "#e6e6e6"
    fg = "#fff" if on else "#777"
    return (f"<span style='display:inline-block;margin:2px 4px 2px 0;padding:2px 8px;"
            f"border-radius:10px;background:{bg};color:{fg};font-size:0.9em'>{html.escape(text)}</span>")


def _indicators_html(ind: Indicators) -> str:
    """The three pills, each with its fixed words, and under them one line that says why: the
    gate that refused a sensor and its value, or what the estimate waits for."""
    pills = [_pill(ind.rest, "standstill", "#2ca02c")]
    why = []
    for sensor in ("acc", "mag"):
        text = getattr(ind, sensor)
        pills.append(_pill(text is not None, f"{sensor} disturbed", "#d62728"))
        if text is not None:
            why.append(f"{sensor} disturbed: {text}")
    if ind.aligning:
        why.insert(0, ind.waiting_for)
    line = html.escape(" · ".join(why))
    color = "#ff7f0e" if ind.aligning else "#d62728"
    return (f"<div style='white-space:nowrap;overflow:hidden'>{''.join(pills)}</div>"
            f"<div title='{line}' style='{_ONE_LINE};font-size:0.85em;color:{color}'>"
            f"{line or '&nbsp;'}</div>")


def _deg3(v) -> str:
    return " ".join(f"{x:7.1f}°" for x in v) if v else "–"


def _offset_row(diag: dict) -> list[tuple[str, str]]:
    """robust's sensor-fixed field offset (a magnet on the phone): its status and size, with
    the vector once it is found (none for an estimator without the fit)."""
    status = diag.get("mag_offset_status")
    if status is None:
        return []
    off = diag.get("mag_offset") or (0.0, 0.0, 0.0)
    size = math.sqrt(sum(float(v) ** 2 for v in off))
    if status == "none":
        text = "none found"
    else:
        vec = "(x y z <code>" + " ".join(f"{float(v):.1f}" for v in off) + "</code>)"
        text = (f"<b>removed</b>: {size:.1f} µT {vec}" if status == "applied"
                else f"fitting: {size:.1f} µT {vec}, not trusted yet")
    return [("magnet on the phone", text)]


def _heading_noise_row(diag: dict) -> list[tuple[str, str]]:
    """robust's heading noise as the data sets it now: the field's heading wander against the
    gyroscope's and the noise density it leads to (the larger, the longer the gyroscope alone
    is trusted); none for an estimator without it."""
    now, wander = diag.get("heading_noise_now"), diag.get("heading_wander")
    if now is None or wander is None:
        return []
    return [("field's heading noise",
             f"{math.degrees(now):.1f} deg·√s (the field wanders {math.degrees(wander):.1f}°)")]


def _readouts_html(st: dict) -> str:
    rates = ", ".join([f"{k} stopped" if v == 0 else f"{k} {v:.0f} Hz"
                       for k, v in sorted(st["rates_hz"].items()) if v is not None]
                      + [f"{k} held back: {why}" for k, why in sorted(st.get("withheld", {}).items())])
    c = st["counts"]
    upd = c["updates"].get(st["primary"], {})

    def used(sensor):
        d = {Reason[k.upper()]: v for k, v in upd.get(sensor, {}).items()}
        # a flagged sample that still enters the estimate (AVERAGED_IN) is counted apart
        kept = sum(v for r, v in d.items() if r in AVERAGED_IN)
        rej = sum(v for r, v in d.items() if is_rejected(r) and r not in AVERAGED_IN)
        return f"{d.get(Reason.USED, 0)} used, " + (f"{kept} accelerating (averaged in), " if kept else "") \
            + f"{rej} rejected"

    err = st["error_to_phone_deg"]
    err_t = st["error_to_truth_deg"]
    bias = (st["estimators"].get(st["primary"]) or {}).get("gyr_bias")
    rows = [
        ("Euler yaw pitch roll", f"<code>{_deg3(st['euler_deg'])}</code>"),
        ("phone's own", f"<code>{_deg3(st['phone_euler_deg'])}</code>"),
        ("vs phone's own", "–" if err is None else f"{err:.2f}°"),
        ("error to truth", "–" if err_t is None else f"{err_t:.2f}°"),
        ("gyro bias used", "–" if bias is None else
         "<code>" + " ".join(f"{math.degrees(b):.2f}" for b in bias) + "</code> deg/s"),
        ("rates", rates or "–"),
        ("acc updates", used("acc")),
        ("mag updates", used("mag")),
        *_offset_row(st.get("diagnostics") or {}),
        *_heading_noise_row(st.get("diagnostics") or {}),
        ("lines", f"{c.get('lines', 0)} ({c.get('malformed', 0)} malformed, "
                  f"{c.get('late', 0)} late)"),
    ]
    body = "".join(f"<tr><td style='color:#666;padding-right:8px'>{k}</td><td>{v}</td></tr>"
                   for k, v in rows)
    return f"<table style='font-size:0.9em'>{body}</table>"


async def run_gui(gui: Gui, hz: float, plot_hz: float | None = None) -> None:
    """Refresh the indicators ``hz`` times a second, and the status line and read-outs
    ``plot_hz`` times (the plots are the landing page's: WS /ws/plots)."""
    loop = asyncio.get_running_loop()
    period = 1.0 / hz
    slow_period = period if plot_hz is None else 1.0 / plot_hz
    due = slow_due = presets_due = loop.time()
    while True:
        try:
            slow = loop.time() >= slow_due - 0.5 * period
            gui.refresh_text(readouts=slow)
            if slow:
                slow_due = max(slow_due + slow_period, loop.time())
            if loop.time() >= presets_due:
                presets_due = loop.time() + PRESETS_REFRESH_S
                gui.refresh_presets()
        except Exception:
            log.exception("GUI refresh failed")
        due = max(due + period, loop.time())      # a steady hz, no catching up after a stall
        await asyncio.sleep(due - loop.time())
