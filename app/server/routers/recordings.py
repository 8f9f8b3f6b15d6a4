"""Recordings: start/stop from the page or a script, list, download, re-run (what-if).

``POST /api/recordings/start`` ``{"name"?}`` and ``POST /api/recordings/stop`` -> ``{name,
path, seconds, samples, bytes, segments, error, stop_reason}``; ``GET /api/recordings``
lists the folder (``--recordings DIR``: our recordings and any app log dropped in it, never
an empty file) with the recorder's state (its size ``bytes`` and rate ``bytes_per_s``
while it runs, the cap that stopped it); a watcher (no token) gets names, sizes and times,
never the presenter's file paths (no ``path``, the folder by its name only); ``GET /api/recordings/{name}/log`` downloads the log (the app's format);
``POST /api/recordings/{name}/rerun`` ``{"patch"?: {estimator: {param: value}}}`` re-runs
it through every estimator (:mod:`app.toolkit.whatif`).
"""

from __future__ import annotations

import asyncio
from typing import Any

from pathlib import Path

from fastapi import APIRouter, Body, Depends, Request
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


def without_paths(x: Any, folder: Path) -> Any:
    """``x`` for a watcher: no ``path`` keys, the folder's absolute path in any text (an
    error message) replaced by its name."""
    full = {str(folder), str(folder.resolve())}
    if isinstance(x, dict):
        return {k: without_paths(v, folder) for k, v in x.items() if k != "path"}
    if isinstance(x, list):
        return [without_paths(v, folder) for v in x]
    if isinstance(x, str):
        for f in sorted(full, key=len, reverse=True):
            if f and f not in (".", "/") and f in x:
                x = x.replace(f, folder.name or "recordings")
        return x
    return x


@router.get("")
async def recordings(request: Request, tk: Toolkit = Depends(get_toolkit)) -> dict:
    """The recordings folder and what the recorder is doing (paths for the presenter
    only)."""
    rs = tk.recording
    listed, left_out = await asyncio.to_thread(rs.scan)     # off the loop: a folder of many
    out = {"folder": str(rs.folder), "status": rs.status(), "recordings": listed,
           "left_out": left_out}
    if not request.app.state.access.is_presenter(request):
        # the folder's other files are the presenter's business (only they can rename them)
        out.pop("left_out")
        out = without_paths(out, rs.folder)
        out["folder"] = rs.folder.name or "recordings"
    return out


@router.post("/start", dependencies=[Depends(require_presenter)])
async def start(body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Start recording the stream on show (``{"name": ...}`` optional)."""
    return tk.recording.start(_body(body, {"name"}).get("name"))


@router.post("/stop", dependencies=[Depends(require_presenter)])
async def stop(tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Stop recording: ``{name, path, seconds, samples, segments, error}``."""
    return tk.recording.stop()


async def _file(tk: Toolkit, name: str, kind: str, missing: str = "") -> Path:
    """Recording ``name``'s file of ``kind`` (log, estimates, events, state), found off the
    loop (a pass over the folder); 404 saying ``missing`` when the recording has none."""
    path = (await asyncio.to_thread(tk.recording.files, name))[kind]
    if path is None:
        raise ToolError("name", f"{name!r} has no {kind} file ({missing})", 404)
    return path


@router.get("/{name}/log")
async def download_log(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The recording's log: as the Sensor Fusion app writes it (text), or the CSV or npz
    dropped into the folder, each with its own type."""
    path = await _file(tk, name, "log")
    kind = {".csv": "text/csv", ".npz": "application/octet-stream"}.get(path.suffix.lower(), "text/plain")
    return FileResponse(path, media_type=kind, filename=path.name)


@router.get("/{name}/estimates")
async def download_estimates(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The estimates recorded beside the log (CSV, gzip-compressed for a recent one)."""
    path = await _file(tk, name, "estimates", "an app log dropped in?")
    media = "application/gzip" if path.name.endswith(".gz") else "text/csv"
    return FileResponse(path, media_type=media, filename=path.name)


@router.get("/{name}/events")
async def download_events(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The recording's events (JSON lines: the settings it began with, every change):
    ``orientlab estimate LOG --config NAME.events.jsonl`` re-runs it with them."""
    path = await _file(tk, name, "events", "an app log dropped in?")
    return FileResponse(path, media_type="application/x-ndjson", filename=path.name)


@router.get("/{name}/state")
async def download_state(name: str, tk: Toolkit = Depends(get_toolkit)) -> FileResponse:
    """The filters' state as the recording began (``NAME.state.npz``, for one begun into
    its stream): beside the log and the events file, a re-run goes on from it."""
    path = await _file(tk, name, "state", "it began with its stream")
    return FileResponse(path, media_type="application/octet-stream", filename=path.name)


@router.post("/{name}/rerun", dependencies=[Depends(require_presenter)])
async def rerun(name: str, body: Any = Body(None), tk: Toolkit = Depends(get_toolkit)) -> dict:
    """Re-run the whole recording through every estimator, before and after ``patch``."""
    return await tk.whatif.rerun(name, _body(body, {"patch"}).get("patch"))
