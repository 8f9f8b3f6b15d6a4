"""Calibration from the page: statistics of the phone lying still (exercise 2), and the
magnetometer's hard and soft iron.

``POST /api/calibrate {"seconds": N}`` waits for N s of the live stream and returns the
statistics (per sensor mean, covariance, σ, normality test, drift per minute, histograms
with the fitted Gaussian, time plots; g0, gyroscope bias and m0 by formula (7)); with
``{"recording": NAME, "from_s"?, "to_s"?}`` a stretch of a recording instead.
``POST /api/calibrate/apply {"save_as"?}`` sets the noise levels, bias, g0 and m0 in the
estimators (and saves a preset). ``POST /api/magcal {"seconds"}`` collects the field while
the phone is turned, ``GET /api/magcal`` shows the coverage and the fit,
``POST /api/magcal/apply {"clear"?, "save_as"?}`` applies it to every MAG sample.
"""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Body, Depends

from app.live.changes import Change, PatchError
from app.server.access import require_presenter
from app.server.lab import LabError, LabTools
from app.server.presets import check_save
from app.server.routers._lab import get_lab, lab_error

router = APIRouter(prefix="/api", tags=["calibration"])
APPLY_TIMEOUT_S = 5.0


def _obj(body: Any, allowed: set[str]) -> dict:
    if body is None:
        body = {}
    if not isinstance(body, dict):
        raise lab_error(LabError("body", "expected a JSON object"))
    unknown = set(body) - allowed
    if unknown:
        raise lab_error(LabError(sorted(unknown)[0], f"unknown key (known: {', '.join(sorted(allowed))})"))
    return body


def _save_refused(e: PatchError):
    """``save_as`` refused by the one preset save path (:func:`app.server.presets.save_preset`):
    422 for the name (its rules, a shipped name, the cap), 507 when the preset folder
    refused the write; the reason either way, never a 500."""
    return lab_error(LabError("save_as", e.reason, getattr(e, "status", 422)))


def _check_save_as(lab: LabTools, b: dict) -> None:
    if b.get("save_as"):
        try:
            check_save(lab.settings, b["save_as"])
        except PatchError as e:
            raise _save_refused(e) from None


async def post_change(engine, change: Change) -> dict:
    done = asyncio.get_running_loop().create_future()
    engine.post(change, done)
    try:
        return await asyncio.wait_for(done, APPLY_TIMEOUT_S)
    except PatchError as e:
        raise lab_error(LabError(".".join(map(str, e.loc)), e.reason)) from None


@router.post("/calibrate", dependencies=[Depends(require_presenter)])
async def calibrate(body: Any = Body(..., examples=[{"seconds": 10}]),
                    lab: LabTools = Depends(get_lab)) -> dict:
    """Keep the phone still: statistics of the next N seconds (or of a recording's stretch)."""
    b = _obj(body, {"seconds", "recording", "from_s", "to_s"})
    try:
        if "recording" in b:
            return await asyncio.get_running_loop().run_in_executor(
                None, lambda: lab.calibrate_recording(b["recording"], b.get("from_s", 0.0), b.get("to_s")))
        if "seconds" not in b:
            raise LabError("seconds", "required (or 'recording')")
        return await lab.calibrate(b["seconds"])
    except LabError as e:
        raise lab_error(e) from None


@router.get("/calibrate")
async def calibration(lab: LabTools = Depends(get_lab)) -> dict:
    """The running calibration's countdown and the last result."""
    cap = lab.capture
    return {"capture": None if cap is None else cap.status(), "result": lab.last_calibration}


@router.post("/calibrate/apply", dependencies=[Depends(require_presenter)])
async def apply_calibration(body: Any = Body(None), lab: LabTools = Depends(get_lab)) -> dict:
    """Set the calibration's noise levels, gyroscope bias, g0 and m0 in the estimators
    (validated; nothing applied if any is refused); ``save_as`` also writes a preset."""
    b = _obj(body, {"save_as"})
    try:
        params = lab.calibration_change()
        body_patch = {"estimators": params}
        change = lab.core.validate(body_patch)
    except LabError as e:
        raise lab_error(e) from None
    except PatchError as e:
        raise lab_error(LabError(".".join(map(str, e.loc)), e.reason)) from None
    _check_save_as(lab, b)    # a refused preset name applies nothing
    view = await post_change(lab.engine, change)
    out = {"applied": params, "params": view}
    if b.get("save_as"):
        try:
            out["preset"] = str(lab.save_calibration_preset(b["save_as"]))
        except PatchError as e:
            raise _save_refused(e) from None
    return out


@router.post("/magcal", dependencies=[Depends(require_presenter)])
async def magcal_start(body: Any = Body(..., examples=[{"seconds": 30}]),
                       lab: LabTools = Depends(get_lab)) -> dict:
    """Turn the phone in all directions for N seconds; GET /api/magcal shows the coverage."""
    b = _obj(body, {"seconds"})
    try:
        return lab.magcal_start(b.get("seconds", 30.0))
    except LabError as e:
        raise lab_error(e) from None


@router.get("/magcal")
async def magcal_status(lab: LabTools = Depends(get_lab)) -> dict:
    return lab.magcal_status()


@router.post("/magcal/apply", dependencies=[Depends(require_presenter)])
async def magcal_apply(body: Any = Body(None), lab: LabTools = Depends(get_lab)) -> dict:
    """Correct every MAG sample with the fit (``{"clear": true}``: stop correcting);
    ``save_as`` also writes a preset holding it (``[magcal]``)."""
    b = _obj(body, {"clear", "save_as"})
    _check_save_as(lab, b)    # a refused preset name applies nothing
    try:
        out = lab.magcal_apply(bool(b.get("clear", False)))
        if b.get("save_as"):
            out["preset"] = str(lab.save_calibration_preset(b["save_as"]))
        return out
    except LabError as e:
        raise lab_error(e) from None
    except PatchError as e:
        raise _save_refused(e) from None
