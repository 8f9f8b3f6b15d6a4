"""The HTTP/WebSocket API, one router per concern."""

from fastapi import HTTPException, Request

from ..engine import Engine, PatchError


def get_engine(request: Request) -> Engine:
    return request.app.state.engine


def unprocessable(e: PatchError) -> HTTPException:
    """A 422 in FastAPI's own error shape, naming the field."""
    loc = [x if isinstance(x, int) else str(x)[:64] for x in e.loc][:8]   # never echo a big input
    return HTTPException(status_code=422, detail=[{"loc": ["body", *loc], "msg": str(e.reason)[:300],
                                                   "type": "value_error"}])
