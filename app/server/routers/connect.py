"""GET /api/connect (presenter only): how each app connects to this PC, and the phone's
status; the QR codes of the Connect tab; phyphox's remote access started from the page."""

from __future__ import annotations

import io

import segno
from fastapi import APIRouter, Body, Depends, HTTPException, Request
from fastapi.responses import Response

from app.server.access import require_presenter, require_presenter_read

router = APIRouter(prefix="/api", tags=["connect"])


@router.get("/connect", dependencies=[Depends(require_presenter_read)])
async def connect(request: Request) -> dict:
    """The addresses each app needs (``sensor_logger.url``, ``phyphox.experiment_url``,
    ``sensorfusion.host``/``port``), the phone slot and what each source detected."""
    return request.app.state.connect.view(request)


QR_OF = {"sensorlogger": lambda v: v["sensor_logger"]["url"],
         "phyphox": lambda v: v["phyphox"]["experiment_url"],
         "sensorfusion": lambda v: f'{v["sensorfusion"]["host"]}:{v["sensorfusion"]["port"]}'}


@router.get("/connect/qr/{app}.svg", dependencies=[Depends(require_presenter_read)],
            include_in_schema=False)
async def connect_qr(request: Request, app: str) -> Response:
    """The QR code of one app's address (SVG)."""
    if app not in QR_OF:
        raise HTTPException(404, f"no QR code for {app[:20]!r}; one of {', '.join(QR_OF)}")
    text = QR_OF[app](request.app.state.connect.view(request))
    buf = io.BytesIO()
    segno.make_qr(text, error="m").save(buf, kind="svg", scale=6, border=2, xmldecl=False)
    return Response(buf.getvalue(), media_type="image/svg+xml",
                    headers={"Cache-Control": "no-store"})


@router.post("/phyphox/poll", dependencies=[Depends(require_presenter)])
async def phyphox_poll(request: Request, url: str | None = Body(None, embed=True)) -> dict:
    """Poll the phyphox phone at ``url`` (the address phyphox shows under "Allow remote
    access", e.g. ``http://192.168.1.40:8080``); ``null`` stops polling."""
    phones = request.app.state.http_phones
    if url is None or url == "":
        phones.stop_poll()
    else:
        try:
            phones.start_poll(url)
        except ValueError as e:
            raise HTTPException(422, [{"loc": ["body", "url"], "msg": str(e)[:200],
                                       "type": "value_error"}]) from None
    return request.app.state.connect.view(request)


@router.post("/sensorlogger/convention", dependencies=[Depends(require_presenter)])
async def sensorlogger_convention(request: Request, convention: str = Body(..., embed=True)) -> dict:
    """The presenter's choice of Sensor Logger's sign convention when the detection is
    unsure: ``auto``, ``android``, ``ios`` (Standardise off) or ``ios-standardised``."""
    try:
        request.app.state.http_phones.set_convention(convention)
    except ValueError as e:
        raise HTTPException(422, [{"loc": ["body", "convention"], "msg": str(e)[:200],
                                   "type": "value_error"}]) from None
    return request.app.state.connect.view(request)
