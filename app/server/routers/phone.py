"""GET/POST /api/phone: the phone slot, one phone at a time across every app (who
streams, the presenter's lock, the presenter's release)."""

from fastapi import APIRouter, Body, Depends, HTTPException, Request
from pydantic import StrictBool

from app.server.access import require_presenter

router = APIRouter(prefix="/api", tags=["phone"])


def slot_status(request: Request) -> dict:
    """The TCP receiver's counts and the shared slot's state; a watcher (no token) does
    not see who streams (a phone's address is the presenter's business)."""
    st = request.app.state
    out = {**st.sensorfusion.status(), "slot": st.slot.status()}
    if not st.access.is_presenter(request):
        out["streaming"] = "a phone" if out["streaming"] else None
        if out["slot"]["holder"] is not None:
            out["slot"]["holder"]["label"] = "a phone"
        for t in out["slot"]["turned_away"]:
            t["who"] = "a phone"
    return out


@router.get("/phone")
async def phone_status(request: Request) -> dict:
    """The phone slot: ``locked`` (no new phone accepted), ``streaming`` (the Sensor
    Fusion app's phone on show, or null), connections ``refused``, closed for sending
    ``no_data``, refused while locked (``refused_locked``); ``slot``: the holder of any
    app, how long it has streamed and been silent, refusals and releases."""
    return slot_status(request)


@router.post("/phone", dependencies=[Depends(require_presenter)])
async def phone_control(request: Request, locked: StrictBool | None = Body(None, embed=True),
                        release: StrictBool | None = Body(None, embed=True)) -> dict:
    """``{"locked": true}`` locks the slot (no new phone; the phone streaming now goes
    on), ``{"locked": false}`` unlocks it; ``{"release": true}`` ends the stream of the
    phone on show (of any app) and keeps that phone out for a while. JSON true or false
    only: ``"yes"`` or ``1`` is refused (422), not read as true."""
    if locked is None and not release:
        raise HTTPException(422, [{"loc": ["body"], "msg": "give locked (true/false) and/or "
                                   "release (true)", "type": "value_error"}])
    slot = request.app.state.slot
    if locked is not None:
        slot.locked = bool(locked)
    if release:
        slot.release("released by the presenter")
    return slot_status(request)
