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
from app.server.routers import get_toolkit
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError

router = APIRouter(prefix="/api/recordings", tags=["recordings"])


def _body(body: Any, allowed: set[str]) -> dict:
    if body is None:
        return {}
    if not isinstance(body, dict):
        raise ToolError("body", "expected a JSON object")
    unknown = set(body) - allowed
    if unknown:
        raise ToolError(sorted(unknown)[0], f"unknown key (known: {', '.join(sorted(allowed))})")
    return body


@router.get("")
async def recordings(tk: Toolkit = Depends(get_toolkit)) -> dict:
    """The recordings folder and what the recorder is doing."""
    rs = tk.recording
    return {"folder": str(rs.folder), "status": rs.status(), "recordings": rs.recordings()}


@router.post("/start", dependencies=[Depends(require_presenter)])
async def start(body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Start recording the stream on show (``{"name": ...}`` optional)."""
    return tk.recording.start(_body(body, {"name"}).get("name"))


@router.post("/stop", dependencies=[Depends(require_presenter)])
async def stop(tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Stop recording: ``{name, path, seconds, samples, segments, error}``."""
    return tk.recording.stop()


@router.get("/{name}/log")
async def download_log(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The recording's log, as the Sensor Fusion app writes it."""
    path = tk.recording.files(name)["log"]
    return FileResponse(path, media_type="text/plain", filename=path.name)


@router.get("/{name}/estimates")
async def download_estimates(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The estimates recorded beside the log (CSV)."""
    path = tk.recording.files(name)["estimates"]
    if path is None:
        raise ToolError("name", f"{name!r} has no estimates file (an app log dropped in?)", 404)
    return FileResponse(path, media_type="text/csv", filename=path.name)


@router.post("/{name}/rerun", dependencies=[Depends(require_presenter)])
async def rerun(name: str, body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Re-run the whole recording through every estimator, before and after ``patch``."""
    return await tk.whatif.rerun(name, _body(body, {"patch"}).get("patch"))
