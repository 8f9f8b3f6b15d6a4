"""The HTTP/WebSocket API, one router per concern."""

from fastapi import HTTPException, Request

from ..engine import Engine, PatchError


def get_engine(request: Request) -> Engine:
    return request.app.state.engine


def unprocessable(e: PatchError) -> HTTPException:
    """A 422 in FastAPI's own error shape, naming the field."""
    return HTTPException(status_code=422, detail=[{"loc": ["body", *e.loc], "msg": e.reason,
                                                   "type": "value_error"}])
