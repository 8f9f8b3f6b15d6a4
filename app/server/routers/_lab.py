"""Shared by the lab toolkit's routers: the toolkit object and its error shape."""

from __future__ import annotations

from fastapi import HTTPException, Request

from app.server.lab import LabError, LabTools


async def get_lab(request: Request) -> LabTools:
    # async: FastAPI runs a plain ``def`` dependency in its thread pool, a thread hop
    # (and a wait for the GIL while the filter runs) on every request
    return request.app.state.lab


def lab_error(e: LabError) -> HTTPException:
    """FastAPI's own error shape (as a 422 does), naming the field; the status says
    what kind of refusal (404 unknown, 409 not now, 422 invalid)."""
    return HTTPException(status_code=e.status, detail=[{"loc": ["body", *str(e.field).split(".")][:8],
                                                        "msg": str(e.reason)[:300],
                                                        "type": "value_error"}])
