"""GET /api/state, GET /api/stats, WS /ws/state, WS /ws/plots, POST /api/source/resume."""

import asyncio
import contextlib

from fastapi import APIRouter, Depends, HTTPException, Request, WebSocket, WebSocketDisconnect

from app.server.access import require_presenter, websocket_origin_ok

from app.server.engine import Engine
from app.server.models import State
from app.server.routers import get_engine

router = APIRouter(tags=["state"])
WS_SEND_TIMEOUT_S = 10.0   # a client that takes longer to accept one message is closed


@router.get("/api/state", response_model=State)
async def state(engine: Engine = Depends(get_engine)) -> dict:
    """The state after the last processed sample."""
    return engine.state()


@router.get("/api/stats")
async def stats(request: Request, reset: bool = False, engine: Engine = Depends(get_engine)) -> dict:
    """Backlog and latency (line arrival to viser update queued), for the load benchmark.
    ``reset=true`` starts a new measurement (the presenter only)."""
    if reset:
        await require_presenter(request)
    access = request.app.state.access
    with access.lock:
        refused = dict(access.refused)
    return {**engine.stats(reset), "access_refused": refused}


@router.post("/api/source/resume", dependencies=[Depends(require_presenter)])
async def resume(engine: Engine = Depends(get_engine)) -> dict:
    """Restart the demo (or log replay) after a phone has left; 409 while a phone streams
    (the demo would take the stream from it)."""
    if not engine.resume_background():
        raise HTTPException(409, "a phone is streaming: the demo resumes after it has left")
    return {"ok": True}


@router.websocket("/ws/state")
async def ws_state(ws: WebSocket) -> None:
    """Every estimate: JSON messages (at most ``ws_hz``, default 20, a second) each
    holding the estimates made since the previous one,
    ``{"primary", "source", "estimates": [{"t", "tag", "q"}]}`` (q of the primary, [w,x,y,z]);
    no estimate is skipped. The first message is the full state (as GET /api/state).
    A client that stops reading (a sleeping laptop) is dropped once it is
    :data:`app.server.engine.SUBSCRIBER_BACKLOG` messages behind, or when one message
    takes longer than ``WS_SEND_TIMEOUT_S`` to send; it never holds up the filter."""
    engine: Engine = ws.app.state.engine
    await _serve(ws, engine.subscribe, engine.unsubscribe, lambda: {"state": engine.state()})


async def _serve(ws: WebSocket, subscribe, unsubscribe, first=None) -> None:
    """One subscriber's WebSocket: the Origin check, ``first()`` (if given) as the first
    message, then every message of its outbox; a client that stops reading or takes
    longer than ``WS_SEND_TIMEOUT_S`` for one message is dropped (close code 1013)."""
    if not websocket_origin_ok(ws):   # a foreign page's script may not listen in
        await ws.close(code=1008)
        return
    await ws.accept()
    sub = subscribe()

    async def watch_close():
        try:
            while True:
                await ws.receive_text()
        except (WebSocketDisconnect, RuntimeError):
            pass
        sub.close()

    watcher = asyncio.create_task(watch_close())
    try:
        if first is not None:
            await asyncio.wait_for(ws.send_json(first()), WS_SEND_TIMEOUT_S)
        while True:
            msg = await sub.next()
            if msg is None:
                break
            await asyncio.wait_for(ws.send_text(msg), WS_SEND_TIMEOUT_S)
    except (WebSocketDisconnect, RuntimeError, OSError, asyncio.TimeoutError):
        pass
    finally:
        unsubscribe(sub)
        watcher.cancel()
        if sub.dropped:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(code=1013), 1.0)


@router.websocket("/ws/plots")
async def ws_plots(ws: WebSocket) -> None:
    """The live plots' points (what the landing page's plot panel draws): JSON messages,
    at most 20 a second while samples come. The first (``"k": "s"``) holds the whole
    window of every plot, each next one (``"k": "d"``) only the new points; a new stream
    starts with a ``"s"`` message again. Columns as lists (``null``: a gap), time in s
    since the stream started (one clock for every plot), at most 25 points a second per
    sensor; see :class:`app.server.gui.plots.PlotFeed`. Watchers may listen too (read
    only); a client that stops reading is dropped as on /ws/state."""
    engine: Engine = ws.app.state.engine
    await _serve(ws, engine.subscribe_plots, engine.unsubscribe_plots)
