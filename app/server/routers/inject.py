"""Disturbance injection: ``POST /api/inject {"kind": "magnet", "strength_uT", "direction",
"seconds", "frame"?}`` or ``{"kind": "shake", "amplitude_ms2", "seconds", "frequency_hz"?}``
adds a virtual magnet or shake to the stream on show (phone, demo or replay); at most
``max_active`` (4) are on at once, one more is refused (409, the message says why and how
long the longest lasts); ``GET /api/inject`` lists the active ones, the cap and the marks
(see :mod:`app.toolkit.inject`)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends

from app.server.access import require_presenter
from app.server.routers import get_toolkit
from app.server.toolkit import Toolkit

router = APIRouter(prefix="/api", tags=["disturbances"])


@router.get("/inject")
async def injections(tk: Toolkit = Depends(get_toolkit)) -> dict:
    return tk.injection.status()


@router.post("/inject", dependencies=[Depends(require_presenter)])
async def inject(body: Any = Body(..., examples=[
        {"kind": "magnet", "strength_uT": 50, "direction": "east", "seconds": 5},
        {"kind": "shake", "amplitude_ms2": 8, "seconds": 3}]),
        tk: Toolkit = Depends(get_toolkit)) -> dict:
    return tk.injection.inject(body)
