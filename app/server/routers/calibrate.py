"""Calibration from the page: statistics of the phone lying still (exercise 2), and the
magnetometer's hard and soft iron.

``POST /api/calibrate {"seconds": N}`` waits for N s of the live stream and returns the
statistics (per sensor mean, covariance, σ, normality test, drift per minute, histograms
with the fitted Gaussian, time plots; g0, gyroscope bias and m0 by formula (7)); with
``{"recording": NAME, "from_s"?, "to_s"?}`` a stretch of a recording instead.
``POST /api/calibrate/apply {"save_as"?, "force"?}`` sets the noise levels, bias, g0 and m0
in the estimators (and saves a preset); a calibration over a phone that moved is refused
(409, the reasons) unless ``"force": true`` (the presenter's "apply anyway"). A
recording's stretch is a heavy job: one at a time, two waiting, more refused (429).
``POST /api/calibrate/bias {"seconds"?, "save_as"?}`` gives lab the gyroscope's bias: the mean
rate of the last N s of the stream, the phone lying still (moved: 409, why).
``POST /api/magcal {"seconds"}`` collects the field while the phone is turned (at most
60,000 samples and the seconds + 5 s of wall time), ``GET /api/magcal`` shows the
coverage and the fit, or why it was refused; ``POST /api/magcal/apply {"clear"?,
"save_as"?}`` applies it to every MAG sample (a refused fit: 409, its reason).
``POST /api/gyro-scale {"recordings": [NAME, ...]}`` fits the gyroscope's scale factor per axis
from recordings in which the phone turns whole turns between rests (``orientlab gyro-scale``;
a heavy job), ``GET /api/gyro-scale`` shows the last fit, ``POST /api/gyro-scale/apply
{"save_as"?}`` sets ``gyr_scale`` of the estimators that have it (no axis measured: 409).
"""

from __future__ import annotations

import math
from typing import Any, Callable

from fastapi import APIRouter, Body, Depends

from app.live.changes import PatchError
from app.server.access import require_presenter
from app.server.routers import get_toolkit
from app.server.toolkit import Toolkit
from app.toolkit.calibration import bias_change, rest_bias
from app.toolkit.errors import ToolError

router = APIRouter(prefix="/api", tags=["calibration"])


def _obj(body: Any, allowed: set[str]) -> dict:
    if body is None:
        body = {}
    if not isinstance(body, dict):
        raise ToolError("body", "expected a JSON object")
    unknown = set(body) - allowed
    if unknown:   # the key named, cut short (the input is never echoed)
        raise ToolError(sorted(unknown)[0][:40], f"unknown key (known: {', '.join(sorted(allowed))})")
    return body


def _stretch(b: dict) -> tuple[str, float, float | None]:
    """A recording's stretch (``recording``, ``from_s``, ``to_s``) checked: a name and
    finite seconds >= 0 (a string or a list for a number was a 500 with a traceback)."""
    name = b["recording"]
    if not isinstance(name, str):
        raise ToolError("recording", "must be the name of a recording (a string)")
    out: list[float | None] = []
    for key, default in (("from_s", 0.0), ("to_s", None)):
        v = b.get(key, default)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))
                              or not math.isfinite(v) or v < 0):
            raise ToolError(key, "must be a number of seconds from the recording's start "
                                 "(finite, >= 0)" + (" or null" if default is None else ""))
        out.append(None if v is None else float(v))
    if out[1] is not None and out[1] <= out[0]:
        raise ToolError("to_s", "must be after from_s")
    return name, out[0], out[1]


async def _apply(tk: Toolkit, params: dict, save_as: str | None,
                 applied: Callable[[], None] | None = None) -> dict:
    """Set a calibration's ``params`` ({estimator: {param: value}}) in the estimators, all or
    nothing (validated first; a refused preset name applies nothing); then ``applied()`` and,
    with ``save_as``, a preset."""
    try:
        change = tk.engine.core.validate({"estimators": params})
    except PatchError as e:
        raise ToolError(".".join(map(str, e.loc)), e.reason) from None
    if save_as:
        tk.check_preset_name(save_as)
    out = {"applied": params, "params": await tk.post(change)}
    if applied is not None:
        applied()
    if save_as:
        out["preset"] = str(tk.save_preset(save_as))
    return out


@router.post("/calibrate", dependencies=[Depends(require_presenter)])
async def calibrate(body: Any = Body(..., examples=[{"seconds": 10}]),
                    tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Keep the phone still: statistics of the next N seconds (or of a recording's stretch)."""
    b = _obj(body, {"seconds", "recording", "from_s", "to_s"})
    cal = tk.calibration
    if "recording" in b:
        name, from_s, to_s = _stretch(b)
        return await cal.calibrate_recording_job(name, from_s, to_s)
    if "from_s" in b or "to_s" in b:
        raise ToolError("from_s" if "from_s" in b else "to_s", "a stretch of a recording: "
                        "give 'recording' too (the live stream takes 'seconds')")
    if "seconds" not in b:
        raise ToolError("seconds", "required (or 'recording')")
    return await cal.calibrate(b["seconds"])


@router.get("/calibrate")
async def calibration(tk: Toolkit = Depends(get_toolkit)) -> dict:
    """The running calibration's countdown and the last result."""
    cap = tk.calibration.capture
    return {"capture": None if cap is None else cap.status(), "result": tk.calibration.last}


@router.post("/calibrate/apply", dependencies=[Depends(require_presenter)])
async def apply_calibration(body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Set the calibration's noise levels, gyroscope bias, g0 and m0 in the estimators
    (validated; nothing applied if any is refused); ``save_as`` also writes a preset. A
    calibration that does not look stationary (the phone moved) is refused with its
    reasons (409) unless ``force`` is true: applying it anyway is the presenter's call."""
    b = _obj(body, {"save_as", "force"})
    force = b.get("force", False)
    if not isinstance(force, bool):
        raise ToolError("force", "must be true or false")
    out = await _apply(tk, tk.calibration.change(force=force), b.get("save_as"),
                       tk.calibration.note_applied)
    out["forced"] = force
    return out


@router.post("/calibrate/bias", dependencies=[Depends(require_presenter)])
async def calibrate_bias(body: Any = Body(None, examples=[{"seconds": 3}]),
                         tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Give lab (which does not estimate it) the gyroscope's bias: the mean rate over the
    last ``seconds`` (0.5-20, default 3) of the stream, in which the phone lay still.
    Refused (409, why) if it moved then or too few samples came; ``save_as`` also writes a
    preset."""
    b = _obj(body, {"seconds", "save_as"})
    core = tk.engine.core
    bias = rest_bias(core, b.get("seconds", 3.0))
    out = await _apply(tk, bias_change(core, bias), b.get("save_as"))
    out["gyr_bias_deg_s"] = [round(math.degrees(x), 4) for x in bias]
    return out


@router.post("/magcal", dependencies=[Depends(require_presenter)])
async def magcal_start(body: Any = Body(..., examples=[{"seconds": 30}]),
                       tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Turn the phone in all directions for N seconds; GET /api/magcal shows the coverage."""
    return tk.magcal.start(_obj(body, {"seconds"}).get("seconds", 30.0))


@router.get("/magcal")
async def magcal_status(tk: Toolkit = Depends(get_toolkit)) -> dict:
    return tk.magcal.status()


@router.post("/magcal/apply", dependencies=[Depends(require_presenter)])
async def magcal_apply(body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Correct every MAG sample with the fit (``{"clear": true}``: stop correcting);
    ``save_as`` also writes a preset holding it (``[magcal]``)."""
    b = _obj(body, {"clear", "save_as"})
    clear = b.get("clear", False)
    if not isinstance(clear, bool):           # "false" (a string) had cleared it
        raise ToolError("clear", "must be true or false")
    if b.get("save_as"):
        tk.check_preset_name(b["save_as"])    # a refused preset name applies nothing
    out = tk.magcal.apply(clear)
    if b.get("save_as"):
        out["preset"] = str(tk.save_preset(b["save_as"]))
    return out


MAX_SCALE_RECORDINGS = 20


@router.post("/gyro-scale", dependencies=[Depends(require_presenter)])
async def gyro_scale(body: Any = Body(..., examples=[{"recordings": ["turns"]}]),
                     tk: Toolkit = Depends(get_toolkit)) -> dict:
    """The gyroscope's scale factor from recordings of one phone (whole turns between rests)."""
    b = _obj(body, {"recordings"})
    names = b.get("recordings")
    if (not isinstance(names, list) or not names or len(names) > MAX_SCALE_RECORDINGS
            or not all(isinstance(n, str) for n in names)):
        raise ToolError("recordings", f"must be a list of 1-{MAX_SCALE_RECORDINGS} recording names")
    return await tk.gyro_scale.fit_job(names)


@router.get("/gyro-scale")
async def gyro_scale_last(tk: Toolkit = Depends(get_toolkit)) -> dict:
    """The last fit (null before the first)."""
    return {"result": tk.gyro_scale.last}


@router.post("/gyro-scale/apply", dependencies=[Depends(require_presenter)])
async def gyro_scale_apply(body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Set the last fit's ``gyr_scale`` (measured axes; 0 for the others) in every estimator that
    has it; ``save_as`` also writes a preset."""
    b = _obj(body, {"save_as"})
    return await _apply(tk, tk.gyro_scale.change(), b.get("save_as"))
