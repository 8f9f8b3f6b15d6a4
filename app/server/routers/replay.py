"""Replay control: ``GET /api/replay``; ``POST /api/replay {"paused", "speed", "seek_s",
"loop"}`` controls the replayed log (speed 0.1-10x, seek in seconds of the log: every
estimator restarts cleanly there); ``{"name": RECORDING}`` starts replaying a recording
of the folder, ``{"stop": true}`` goes back to the demo."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends

from app.server.access import require_presenter
from app.server.routers import get_toolkit
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError

router = APIRouter(prefix="/api", tags=["replay"])
KEYS = {"paused", "speed", "seek_s", "loop", "name", "stop"}


@router.get("/replay")
async def replay_status(tk: Toolkit = Depends(get_toolkit)) -> dict:
    return tk.replay.status()


@router.post("/replay", dependencies=[Depends(require_presenter)])
async def replay(body: Any = Body(..., examples=[{"paused": False, "speed": 2.0, "seek_s": 30.0}]),
                 tk: Toolkit = Depends(get_toolkit)) -> dict:
    if not isinstance(body, dict):
        raise ToolError("body", "expected a JSON object")
    unknown = set(body) - KEYS
    if unknown:
        raise ToolError(sorted(unknown)[0], f"unknown key (known: {', '.join(sorted(KEYS))})")
    rs = tk.replay
    if body.get("stop"):
        rs.stop()
        return rs.status()
    if "name" in body:
        rs.start(body["name"])
    rs.set(paused=body.get("paused"), speed=body.get("speed"), seek_s=body.get("seek_s"),
           loop=body.get("loop"))
    return rs.status()
