"""Replay control: ``GET /api/replay``; ``POST /api/replay {"paused", "speed", "seek_s",
"loop"}`` controls the replayed log (speed 0.1-10x, seek in seconds of the log: every
estimator restarts cleanly there); ``{"name": RECORDING}`` starts replaying a recording
of the folder, ``{"stop": true}`` goes back to the demo."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends, Request

from app.server.access import require_presenter
from app.server.lab import LabError, LabTools
from app.sources.runners import ReplayError
from app.server.routers._lab import get_lab, lab_error

router = APIRouter(prefix="/api", tags=["replay"])
KEYS = {"paused", "speed", "seek_s", "loop", "name", "stop"}


@router.get("/replay")
async def replay_status(lab: LabTools = Depends(get_lab)) -> dict:
    return lab.replay_status()


@router.post("/replay", dependencies=[Depends(require_presenter)])
async def replay(request: Request, body: Any = Body(..., examples=[{"paused": False, "speed": 2.0, "seek_s": 30.0}]),
                 lab: LabTools = Depends(get_lab)) -> dict:
    try:
        if not isinstance(body, dict):
            raise LabError("body", "expected a JSON object")
        unknown = set(body) - KEYS
        if unknown:
            raise LabError(sorted(unknown)[0], f"unknown key (known: {', '.join(sorted(KEYS))})")
        if body.get("stop"):
            lab.stop_replay(request.app.state)
            return lab.replay_status()
        if "name" in body:
            lab.start_replay(request.app.state, body["name"])
        if lab.replay is None:
            raise LabError("name", "nothing is replayed: give a recording's name", 409)
        lab.replay.set(paused=body.get("paused"), speed=body.get("speed"),
                       seek_s=body.get("seek_s"), loop=body.get("loop"))
        return lab.replay_status()
    except ReplayError as e:
        raise lab_error(LabError(e.field, e.reason)) from None
    except LabError as e:
        raise lab_error(e) from None
