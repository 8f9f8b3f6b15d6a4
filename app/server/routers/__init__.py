"""The HTTP/WebSocket API, one router per concern."""

from fastapi import HTTPException, Request

from app.server.engine import Engine, PatchError


async def get_engine(request: Request) -> Engine:
    # async: FastAPI runs a plain ``def`` dependency in its thread pool, a thread hop
    # (and a wait for the GIL while the filter runs) on every request
    return request.app.state.engine


def unprocessable(e: PatchError) -> HTTPException:
    """A 422 in FastAPI's own error shape, naming the field."""
    loc = [x if isinstance(x, int) else str(x)[:64] for x in e.loc][:8]   # never echo a big input
    return HTTPException(status_code=422, detail=[{"loc": ["body", *loc], "msg": str(e.reason)[:300],
                                                   "type": "value_error"}])
