"""The Lab tab's what-if: re-run a recording with one parameter of one estimator changed,
and show before against after (the table, the error and the yaw). The same operation as
``POST /api/recordings/{name}/rerun`` (:class:`app.toolkit.whatif.WhatIfService`); the
controls offer the estimator, the parameter and the value from lists, the value in the
unit shown.

:class:`WhatIfPanel` is built by :class:`app.server.gui.toolkit_tab.ToolkitTab` inside its
folder, runs its callbacks through the tab's (``call``: onto the event loop; ``notify``: a
refusal back to the tab that clicked) and is refreshed by it (:meth:`WhatIfPanel.refresh`).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from app.server.gui.plots import unwrap_deg
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError
from app.toolkit.whatif import first_suggestion


class WhatIfPanel:
    """The what-if's controls in the current GUI container; ``plot(title, labels, height)``
    makes a chart there."""

    def __init__(self, gui, tk: Toolkit, call: Callable, notify: Callable, plot: Callable):
        self.gui = gui
        self.tk = tk
        self.core = tk.engine.core
        self._call = call
        self._notify = notify
        self._plot = plot
        self.result: dict[str, Any] | None = None     # the last re-run's answer
        self._build()

    def _build(self) -> None:
        gui = self.gui
        self.recording = gui.add_dropdown("Recording ", ("(none)",))
        # estimator, parameter and value from lists, the value in the unit shown
        # (the API takes the same change as JSON: POST /api/recordings/{name}/rerun)
        est0, par0, val0 = first_suggestion(self.tk.whatif.specs(), self.core.ensemble.primary)
        self.est = gui.add_dropdown("Estimator", self.estimators(), initial_value=est0)
        self._primary = self.core.ensemble.primary   # the primary it was last set to
        self.rows: dict[str, dict[str, Any]] = {}
        labels = self._param_labels(est0)
        self.param = gui.add_dropdown(
            "Parameter", labels, initial_value=next(
                (lab for lab, r in self.rows.items() if r["name"] == par0), labels[0]))
        self.value = gui.add_number("Value", 0.0, step=0.001,
                                    hint="the new value, in the unit of the parameter's name")
        self.choice = gui.add_dropdown("Value ", ("off", "on"), initial_value="off",
                                       hint="the new setting")
        self.now_md = gui.add_markdown("")
        self._show_value(suggested=val0)
        self.est.on_update(lambda ev: ev.client is not None and self._call(self.pick_estimator))
        self.param.on_update(lambda ev: ev.client is not None and self._call(self._show_value))
        wb = gui.add_button("Re-run before/after",
                            hint="POST /api/recordings/{name}/rerun {patch: {estimator: {param: value}}}")
        wb.on_click(self._rerun)
        self.md = gui.add_markdown("")
        self.p_err = self._plot("error [deg] before (solid) vs after (dashed)",
                                ["before", "after"], height=170)
        self.p_yaw = self._plot("yaw [deg] before vs after", ["before", "after"], height=170)

    def estimators(self) -> tuple[str, ...]:
        """The estimators a change can go to (the phone's own estimate is the reference)."""
        b = self.core.ensemble
        return tuple(n for n in b.names if not b.is_reference(n)) or tuple(b.names)

    def _param_labels(self, est: str) -> tuple[str, ...]:
        """``est``'s tunable parameters with a single value (a switch, a choice, a number)
        as ``name [unit shown]``; fills ``rows`` (label -> its row of ``describe``)."""
        from app.params import describe
        p = self.core.ensemble.params_of(est)
        self.rows = {}
        for row in describe(type(p)):
            v = getattr(p, row["name"])
            if not row["tunable"] or v is None or isinstance(v, (tuple, list)):
                continue
            unit = row["user_unit"] or ""
            plain = isinstance(v, bool) or row["choices"] or not unit
            self.rows[row["name"] if plain else f"{row['name']} [{unit}]"] = {**row, "now": v}
        return tuple(self.rows) or ("(none)",)

    def pick_estimator(self) -> None:
        name = self.param.value.split(" [")[0]
        labels = self._param_labels(self.est.value)
        self.param.options = labels
        self.param.value = next((lab for lab, r in self.rows.items() if r["name"] == name),
                                   labels[0])
        self._show_value()

    def _show_value(self, suggested: Any = None) -> None:
        """The value controls for the picked parameter: its current value (or the
        suggestion), in the unit shown; a switch or a choice as a dropdown."""
        from app.server.gui.controls import fmt, precision_for
        row = self.rows.get(self.param.value)
        if row is None:
            self.value.visible = self.choice.visible = False
            self.now_md.content = ""
            return
        try:    # the value in force now (the Tuning tab or the API may have changed it)
            row["now"] = getattr(self.core.ensemble.params_of(self.est.value), row["name"])
        except (KeyError, AttributeError):
            pass
        now = row["now"]
        # a switch is offered turned over (a re-run with the value in force changes nothing);
        # a number or a choice as it is, to be changed
        new = (not now if isinstance(now, bool) else now) if suggested is None else suggested
        unit = row["user_unit"] or ""
        if isinstance(now, bool) or row["choices"]:
            opts = ("off", "on") if isinstance(now, bool) else tuple(str(c) for c in row["choices"])
            show = (lambda v: ("on" if v else "off")) if isinstance(now, bool) else str
            self.choice.options = opts
            self.choice.value = show(new)
            self.choice.visible, self.value.visible = True, False
            txt = f"now: **{show(now)}**"
        else:
            scale = float(row["user_scale"] or 1.0)
            v = float(new) * scale
            p = 0 if row["integer"] else precision_for(v)
            self.value.precision = p
            self.value.step = 10.0 ** -p
            self.value.value = v
            self.value.visible, self.choice.visible = True, False
            txt = f"now: **{fmt(float(now) * scale)} {unit}**".rstrip()
        if suggested is not None:
            txt += " -- suggested first try: switch the magnetometer off (heading from the " \
                   "gyroscope alone)" if row["name"] == "use_mag" else " -- suggested first try"
        self.now_md.content = txt

    def change(self) -> dict[str, Any]:
        """The change the controls show, as the API's patch of one estimator (SI)."""
        row = self.rows.get(self.param.value)
        if row is None:
            raise ToolError("param", "pick a parameter")
        now = row["now"]
        if isinstance(now, bool):
            return {row["name"]: self.choice.value == "on"}
        if row["choices"]:
            choices = tuple(row["choices"])
            return {row["name"]: choices[[str(c) for c in choices].index(self.choice.value)]}
        v = float(self.value.value) / float(row["user_scale"] or 1.0)
        return {row["name"]: int(round(v)) if row["integer"] else v}

    def _rerun(self, ev) -> None:
        async def run():
            try:
                changes = self.change()
            except ToolError as e:
                self._notify(ev, "What-if", e.reason)
                return
            self.md.content = "re-running..."
            try:
                out = await self.tk.whatif.rerun(self.recording.value, {self.est.value: changes})
            except ToolError as e:
                self.md.content = ""
                self._notify(ev, "What-if", f"{e.field}: {e.reason}")
                return
            self.result = out
            self.draw()
        self._call(run)

    def draw(self) -> None:
        """The what-if's table: one short row per estimator (units in the header, numbers
        rounded to 0.1°), what the numbers are and why the re-run and the live filter
        differ, in words below it."""
        out = self.result
        if out is None:
            return
        ref = out["reference"]
        key = {"truth": "error_to_truth_deg", "phone": "error_to_phone_deg"}.get(ref or "")
        ests = out["estimators"]
        live = key is not None and any((e.get("live") or {}).get(key) for e in ests.values())

        def deg(x):
            return "-" if x is None else (f"{x:.0f}" if abs(x) >= 100 else f"{x:.1f}")

        def rms(run, k=key):
            return None if run is None or k is None or run.get(k) is None else run[k].get("rms")
        what = {"truth": "to truth", "phone": "vs phone's own"}.get(ref or "", "")
        rows = [f"**{out['name']}**: {out['duration_s']:.0f} s re-run in {out['estimate_s']:.1f} s", ""]
        if key is None:
            rows += ["| estimator | change [°] |", "|---|---|"]
            rows += [f"| {n} | {deg((e.get('change_deg') or {}).get('rms'))} |"
                     for n, e in ests.items() if not e.get("reference")]
        else:
            rows[0] += f"; RMS error {what} [°]:"
            # live: at the rows the recording kept its estimates for; in brackets the
            # re-run's "before" at the same rows (like for like)
            rows += ["| estimator |" + (" live (re-run there) |" if live else "") + " before | after |",
                     "|---|" + ("---|" if live else "") + "---|---|"]
            for n, e in ests.items():
                lv = e.get("live")
                cell = deg(rms(lv)) + ("" if not lv or not lv.get("rerun") else
                                       f" ({deg(rms(lv['rerun']))})")
                cells = [n] + ([cell] if live else []) + \
                    [deg(rms(e["before"])), deg(rms(e["after"]))]
                rows.append("| " + " | ".join(cells) + " |")
        sel = ests.get(self.est.value)
        if sel is not None and sel.get("before") and sel["before"]["rejected"]["mag"] is not None:
            b = 100 * sel["before"]["rejected"]["mag"]
            a = sel["after"]["rejected"]["mag"] if sel.get("after") else None
            rows += ["", f"{self.est.value}: magnetometer refused {b:.0f} %"
                     + ("" if a is None else f" before, {100 * a:.0f} % after")]
        words = [f"*{x}.*" for x in out.get("notes", [])]
        words += [f"*{n}: {e['note']}.*" for n, e in ests.items() if e.get("note")]
        self.md.content = "\n\n".join(["\n".join(rows)] + words)
        e = out["estimators"].get(self.est.value)
        t = np.array(out["t"], dtype=float)
        if e is None or e["before"] is None:
            return
        after = e["after"] or e["before"]

        def arr(x):
            return np.array([np.nan if v is None else v for v in (x or [])], dtype=float) \
                if x is not None else np.full(len(t), np.nan)
        for plot, key in ((self.p_err, "error_deg"), (self.p_yaw, "yaw_deg")):
            a, b2 = arr(e["before"]["series"][key]), arr(after["series"][key])
            ok = np.isfinite(a) & np.isfinite(b2)   # uPlot's autoscale fails on NaN: drop them
            if key == "yaw_deg" and ok.any():
                a[ok], b2[ok] = unwrap_deg(np.column_stack((a[ok], b2[ok])), align=True).T
            plot.data = (t[ok], a[ok], b2[ok]) if ok.any() else (np.zeros(2),) * 3

    def refresh(self, recordings: tuple[str, ...]) -> None:
        """The lists as they are now: the recordings, the estimators (a variant added or
        removed), the primary (a new one is followed unless a viewer picked another)."""
        if tuple(self.recording.options) != recordings:
            v = self.recording.value
            new = [r for r in recordings if r not in self.recording.options]
            self.recording.options = recordings
            if new and new[0] != "(none)":     # one just recorded (the list is newest first)
                self.recording.value = new[0]
            elif v in recordings:
                self.recording.value = v
        b = self.core.ensemble
        if tuple(self.est.options) != self.estimators():
            picked = self.est.value
            self.est.options = self.estimators()
            if picked not in self.est.options:     # a variant removed: its parameters go
                self.est.value = self.est.options[0]
                self.pick_estimator()
        if b.primary != self._primary:
            # a new primary: the what-if goes to it too, unless a viewer picked another
            if self.est.value == self._primary and b.primary in self.est.options:
                self.est.value = b.primary
                self.pick_estimator()
            self._primary = b.primary
