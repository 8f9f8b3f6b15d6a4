"""GET/POST /api/phone: the phone slot (who streams, the presenter's lock)."""

from fastapi import APIRouter, Body, Depends, Request

from ..access import require_presenter

router = APIRouter(prefix="/api", tags=["phone"])


@router.get("/phone")
async def phone_status(request: Request) -> dict:
    """The phone slot: ``locked`` (no new phone accepted), ``streaming`` (the phone on
    show, or null), connections ``refused``, closed for sending ``no_data``, refused while locked (``refused_locked``)."""
    return request.app.state.phone.status()


@router.post("/phone", dependencies=[Depends(require_presenter)])
async def phone_lock(request: Request, locked: bool = Body(..., embed=True)) -> dict:
    """Lock (``{"locked": true}``) or unlock the phone slot; the phone streaming now
    goes on either way."""
    phone = request.app.state.phone
    phone.locked = bool(locked)
    return phone.status()
