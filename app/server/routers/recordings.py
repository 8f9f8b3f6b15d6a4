"""Recordings: start/stop from the page or a script, list, download, re-run (what-if).

``POST /api/recordings/start`` ``{"name"?}`` and ``POST /api/recordings/stop`` -> ``{name,
path, seconds, samples, segments, error}``; ``GET /api/recordings`` lists the folder
(``--recordings DIR``: our recordings and any app log dropped in it) with the recorder's
state; ``GET /api/recordings/{name}/log`` downloads the log (the app's format);
``POST /api/recordings/{name}/rerun`` ``{"patch"?: {estimator: {param: value}}}`` re-runs
it through every estimator (:mod:`app.toolkit.whatif`).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends
from fastapi.responses import FileResponse

from app.server.access import require_presenter
from app.server.lab import LabError, LabTools
from app.server.routers._lab import get_lab, lab_error

router = APIRouter(prefix="/api/recordings", tags=["recordings"])


def _body(body: Any) -> dict:
    if body is None:
        return {}
    if not isinstance(body, dict):
        raise lab_error(LabError("body", "expected a JSON object"))
    return body


@router.get("")
async def recordings(lab: LabTools = Depends(get_lab)) -> dict:
    """The recordings folder and what the recorder is doing."""
    return {"folder": str(lab.folder), "status": lab.recording_status(),
            "recordings": lab.recordings()}


@router.post("/start", dependencies=[Depends(require_presenter)])
async def start(body: Any = Body(None), lab: LabTools = Depends(get_lab)) -> dict:
    """Start recording the stream on show (``{"name": ...}`` optional)."""
    b = _body(body)
    unknown = set(b) - {"name"}
    try:
        if unknown:
            raise LabError(sorted(unknown)[0], "unknown key (known: name)")
        return lab.start_recording(b.get("name"))
    except LabError as e:
        raise lab_error(e) from None


@router.post("/stop", dependencies=[Depends(require_presenter)])
async def stop(lab: LabTools = Depends(get_lab)) -> dict:
    """Stop recording: ``{name, path, seconds, samples, segments, error}``."""
    try:
        return lab.stop_recording()
    except LabError as e:
        raise lab_error(e) from None


@router.get("/{name}/log")
async def download_log(name: str, lab: LabTools = Depends(get_lab)) -> FileResponse:
    """The recording's log, as the Sensor Fusion app writes it."""
    try:
        path = lab.files(name)["log"]
    except LabError as e:
        raise lab_error(e) from None
    return FileResponse(path, media_type="text/plain", filename=path.name)


@router.get("/{name}/estimates")
async def download_estimates(name: str, lab: LabTools = Depends(get_lab)) -> FileResponse:
    """The estimates recorded beside the log (CSV)."""
    try:
        path = lab.files(name)["estimates"]
        if path is None:
            raise LabError("name", f"{name!r} has no estimates file (an app log dropped in?)", 404)
    except LabError as e:
        raise lab_error(e) from None
    return FileResponse(path, media_type="text/csv", filename=path.name)


@router.post("/{name}/rerun", dependencies=[Depends(require_presenter)])
async def rerun(name: str, body: Any = Body(None), lab: LabTools = Depends(get_lab)) -> dict:
    """Re-run the whole recording through every estimator, before and after ``patch``."""
    b = _body(body)
    try:
        unknown = set(b) - {"patch"}
        if unknown:
            raise LabError(sorted(unknown)[0], "unknown key (known: patch)")
        return await lab.rerun(name, b.get("patch"))
    except LabError as e:
        raise lab_error(e) from None
