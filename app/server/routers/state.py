"""GET /api/state, GET /api/stats, WS /ws/state, POST /api/source/resume."""

import asyncio

from fastapi import APIRouter, Depends, WebSocket, WebSocketDisconnect

from ..engine import Engine
from ..models import State
from . import get_engine

router = APIRouter(tags=["state"])
WS_QUEUE_MAX = 10_000   # batches; a client that falls this far behind is dropped


@router.get("/api/state", response_model=State)
async def state(engine: Engine = Depends(get_engine)) -> dict:
    """The state after the last processed sample."""
    return engine.state()


@router.get("/api/stats")
async def stats(reset: bool = False, engine: Engine = Depends(get_engine)) -> dict:
    """Backlog and latency (line arrival to viser update queued), for the load benchmark.
    ``reset=true`` starts a new measurement."""
    return engine.stats(reset)


@router.post("/api/source/resume")
async def resume(engine: Engine = Depends(get_engine)) -> dict:
    """Restart the demo (or log replay) after a phone has left."""
    engine.resume_background()
    return {"ok": True}


@router.websocket("/ws/state")
async def ws_state(ws: WebSocket) -> None:
    """Every estimate: JSON messages (at most ``ws_hz``, default 20, a second) each
    holding the estimates made since the previous one,
    ``{"primary", "source", "estimates": [{"t", "tag", "q"}]}`` (q of the primary, [w,x,y,z]);
    no estimate is skipped. The first message is the full state (as GET /api/state)."""
    engine: Engine = ws.app.state.engine
    await ws.accept()
    q: asyncio.Queue = asyncio.Queue(maxsize=WS_QUEUE_MAX)
    await ws.send_json({"state": engine.state()})
    engine.subscribers.add(q)

    async def watch_close():
        try:
            while True:
                await ws.receive_text()
        except (WebSocketDisconnect, RuntimeError):
            pass
        q.put_nowait(None)

    watcher = asyncio.create_task(watch_close())
    try:
        while True:
            msg = await q.get()
            if msg is None:
                break
            await ws.send_text(msg)
    except (WebSocketDisconnect, RuntimeError, asyncio.QueueFull):
        pass
    finally:
        engine.subscribers.discard(q)
        watcher.cancel()
