"""The phone apps that push over HTTP, on the dashboard's own port (no token: a phone has
none; the phone slot decides who streams).

- ``POST /sensorlogger``: Sensor Logger's HTTP push (the URL typed into the app);
- ``POST /phyphox``: the pushes of orientlab's phyphox experiment;
- ``GET /phyphox/orientlab.phyphox``: that experiment, with this PC's LAN address baked
  in (phyphox loads it from the QR code on the Connect tab).

Each answers at once: read the body (on a worker thread), enqueue, reply (200; 400 with
the reason for a malformed body; 413 over the body cap; Sensor Logger 499 with the
reason, which the app shows, when another phone holds the slot; phyphox 409, which it
shows as a network error).
"""

from __future__ import annotations

import logging
import time

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import PlainTextResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from app.server.access import phone_push
from app.sources.phyphox import experiment_xml

router = APIRouter(tags=["phones"], dependencies=[Depends(phone_push)])
log = logging.getLogger("orientlab.push")
WRONG_PUSH_LOG_S = 5.0     # at most one terminal line this often about pushes to nowhere


def install_wrong_address_answer(app: FastAPI) -> None:
    """A POST that finds no route outside the API (a phone app given the page's address
    without ``/sensorlogger``, or Sensor Logger's own example ``/data``): the reply says
    where pushes go, and the terminal says so once every :data:`WRONG_PUSH_LOG_S` s (the
    app shows nothing of a 404, so the teacher's terminal is where it shows)."""
    last_said = [0.0]

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        path = request.url.path
        if exc.status_code in (404, 405) and request.method == "POST" and not path.startswith("/api/"):
            now = time.monotonic()
            if now - last_said[0] >= WRONG_PUSH_LOG_S:
                last_said[0] = now
                log.warning("a push to %s found nothing here: a phone app's push address ends in "
                            "/sensorlogger (Sensor Logger) or /phyphox (the experiment's)",
                            ascii(path[:80]))
            return PlainTextResponse("orientlab: no pushes are taken here: Sensor Logger's push "
                                     "address ends in /sensorlogger", status_code=exc.status_code)
        return await http_exception_handler(request, exc)


async def _push(request: Request, phone_app: str) -> PlainTextResponse:
    client = request.client.host if request.client else "?"
    phones = request.app.state.http_phones
    refused = phones.refusal(phone_app, client)      # before the body is read: a refused
    if refused is not None:                          # phone's 16 MB cost nothing but its head
        return PlainTextResponse(refused.text, status_code=refused.status)
    try:
        body = await request.body()
    except ClientDisconnect:     # a push cut off mid-body (the Wi-Fi dropped): counted, no trace
        phones.count_cut(phone_app)
        return PlainTextResponse("the push was cut off", status_code=400)
    reply = await phones.push(phone_app, body, client)
    return PlainTextResponse(reply.text, status_code=reply.status)


@router.post("/sensorlogger")
async def sensorlogger_push(request: Request) -> PlainTextResponse:
    """Sensor Logger's HTTP push: one JSON message (``messageId``, ``sessionId``,
    ``deviceId``, ``payload`` of readings)."""
    return await _push(request, "sensorlogger")


@router.post("/phyphox")
async def phyphox_push(request: Request) -> PlainTextResponse:
    """The pushes of orientlab's phyphox experiment (one JSON object of buffers)."""
    return await _push(request, "phyphox")


# What a phone's browser shows when the push address is opened there (a student scans the
# Connect tab's code with the camera, or checks the address): it answered 405 "Method Not
# Allowed", read as a broken server; now it says the address works and what to do with it.
_ADDRESS_OK = {
    "sensorlogger": "orientlab: this is the Sensor Logger push address, and this phone "
                    "reaches the PC. Type this address in Sensor Logger's settings: Data "
                    "Streaming > HTTP Push, on; tick the sensors, then press Record in the app.",
    "phyphox": "orientlab: this is the push address of orientlab's phyphox experiment, and "
               "this phone reaches the PC. Load the experiment from the code on the Connect "
               "tab (phyphox: + > Scan QR code), then press its start button.",
}


@router.get("/sensorlogger", include_in_schema=False)
async def sensorlogger_address() -> PlainTextResponse:
    return PlainTextResponse(_ADDRESS_OK["sensorlogger"])


@router.get("/phyphox", include_in_schema=False)
async def phyphox_address() -> PlainTextResponse:
    return PlainTextResponse(_ADDRESS_OK["phyphox"])


@router.get("/privacy", include_in_schema=False)
async def privacy() -> PlainTextResponse:
    """The data policy phyphox shows before a pushing experiment may run."""
    return PlainTextResponse(
        "orientlab: while you measure, this experiment sends your phone's accelerometer, "
        "gyroscope, magnetometer and attitude readings, their times and the phone's model "
        "name to the orientlab dashboard on this network (the lab PC), nowhere else. They "
        "are shown live and kept only if the presenter records the session.\n")


@router.get("/phyphox/orientlab.phyphox")
async def phyphox_experiment(request: Request) -> Response:
    """orientlab's phyphox experiment: accelerometer (with g), gyroscope, magnetometer and
    attitude at the fastest rate, pushed to this PC every 0.1 s while measuring."""
    base = request.app.state.connect.base_url(request)
    xml = experiment_xml(f"{base}/phyphox")
    return Response(xml, media_type="application/xml",
                    headers={"Content-Disposition": 'attachment; filename="orientlab.phyphox"'})
