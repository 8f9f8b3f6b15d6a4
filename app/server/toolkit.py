"""The lab's tools on the live server: one :class:`Toolkit` per dashboard, built in the
lifespan, holding the toolkit's services (:mod:`app.toolkit`) wired to the engine. The
routers reach it through :func:`app.server.routers.get_toolkit`, the Lab tab through its
constructor. Everything here runs on the server's event loop.

The stream's samples (of any source) pass, in order: the injection (a virtual magnet or
shake, marked by TXT samples) -> the recording (the log is what the estimators got,
before the magnetometer calibration) -> the magnetometer calibration (hard and soft iron,
applied to MAG) -> the core (reorder, estimators): the services are built in that order,
each appending its stage to ``core.sample_stages``.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.live.changes import Change, PatchError
from app.server.background import ReplayService
from app.server.engine import Engine
from app.server.presets import check_save, save_preset
from app.toolkit.calibration import CalibrationService
from app.toolkit.errors import ToolError
from app.toolkit.gyro_scale import GyroScaleService
from app.toolkit.inject import InjectionService
from app.toolkit.magcal import MagCalService
from app.toolkit.recording import RecordingLimits
from app.toolkit.session_recorder import RecordingService
from app.toolkit.variants import VariantService
from app.toolkit.whatif import WhatIfService

CHANGE_TIMEOUT_S = 5.0


@dataclass
class Toolkit:
    engine: Engine
    settings: Any
    injection: InjectionService
    recording: RecordingService
    magcal: MagCalService
    calibration: CalibrationService
    gyro_scale: GyroScaleService
    whatif: WhatIfService
    variants: VariantService
    replay: ReplayService

    @classmethod
    def build(cls, engine: Engine, settings, config: dict[str, Any] | None,
              tasks: dict[str, asyncio.Task]) -> Toolkit:
        core = engine.core
        folder = Path(getattr(settings, "recordings", None) or "recordings")
        injection = InjectionService(core)                            # stage 1
        recording = RecordingService(core, folder, engine.preset_parts,    # stage 2
                                     RecordingLimits.from_settings(settings))
        magcal = MagCalService(core, (config or {}).get("magcal"))   # stage 3
        injection.mark_listeners.append(recording.note_mark)
        engine.param_listeners.append(recording.note_params)
        engine.change_listeners.append(magcal.on_change)
        engine.preset_parts.append(magcal.preset_part)
        recording.record_parts.append(magcal.record_part)
        recording.queued = engine.queued_samples        # a recording begun into its stream
        recording.undo_later_stages = magcal.uncorrect
        magcal.listeners.append(recording.note_params)
        files = recording.files
        return cls(engine=engine, settings=settings, injection=injection, recording=recording,
                   magcal=magcal, calibration=CalibrationService(core, files),
                   gyro_scale=GyroScaleService(core, files),
                   whatif=WhatIfService(core, files), variants=VariantService(core),
                   replay=ReplayService(engine, settings, tasks, files))

    def tick(self) -> None:
        """A few times a second: end a recording segment whose stream ended, give up a
        calibration whose stream stopped."""
        self.recording.tick()
        self.calibration.tick()
        self.magcal.tick()

    def close(self) -> None:
        """At shutdown: a recording ends cleanly."""
        if self.recording.recording:
            self.recording.stop()

    async def post(self, change: Change) -> dict:
        """Apply ``change`` on the filter task; its view, or ToolError naming the field."""
        try:
            return await self.engine.apply(change, CHANGE_TIMEOUT_S)
        except PatchError as e:
            raise ToolError(".".join(map(str, e.loc)), e.reason) from None

    def check_preset_name(self, name: str) -> None:
        """ToolError("save_as") unless a preset may be saved as ``name`` (before anything
        is applied, so a refused name applies nothing)."""
        try:
            check_save(self.settings, name)
        except PatchError as e:
            raise _save_refused(e) from None

    def save_preset(self, name: str) -> Path:
        """The current parameters with the calibration's values and the magnetometer
        calibration in force, as a preset (what "apply" then "save" gives), by the one
        save path of every preset (:func:`app.server.presets.save_preset`: name rules,
        no shipped name, the cap, an atomic write); ToolError("save_as") if refused
        (422 for the name, 507 when the folder refused the write)."""
        try:
            return save_preset(self.engine, name, header=self.calibration.preset_header())
        except PatchError as e:
            raise _save_refused(e) from None


def _save_refused(e: PatchError) -> ToolError:
    return ToolError("save_as", e.reason, getattr(e, "status", 422))
