"""The HTTP/WebSocket API, one router per concern."""

from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import JSONResponse

from app.server.engine import Engine, EngineBusy, PatchError
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError


async def get_engine(request: Request) -> Engine:
    # async: FastAPI runs a plain ``def`` dependency in its thread pool, a thread hop
    # (and a wait for the GIL while the filter runs) on every request
    return request.app.state.engine


async def get_toolkit(request: Request) -> Toolkit:
    """The lab's tools (:class:`app.server.toolkit.Toolkit`), built in the lifespan."""
    return request.app.state.toolkit


def unprocessable(e: PatchError) -> HTTPException:
    """A 422 in FastAPI's own error shape, naming the field."""
    loc = [x if isinstance(x, int) else str(x)[:64] for x in e.loc][:8]   # never echo a big input
    return HTTPException(status_code=422, detail=[{"loc": ["body", *loc], "msg": str(e.reason)[:300],
                                                   "type": "value_error"}])


def tool_error_response(e: ToolError) -> JSONResponse:
    """A tool's refusal in FastAPI's own error shape (as a 422 is), naming the field; the
    status says what kind of refusal (404 unknown, 409 not now, 422 invalid)."""
    detail = [{"loc": ["body", *str(e.field).split(".")][:8], "msg": str(e.reason)[:300],
               "type": "value_error"}]
    return JSONResponse({"detail": detail}, status_code=e.status)


def install_tool_errors(app: FastAPI) -> None:
    """Every ToolError a route lets through becomes :func:`tool_error_response`; an
    :class:`EngineBusy` (a change the filter task did not take in time) a 503."""

    @app.exception_handler(ToolError)
    async def _tool_error(request: Request, exc: ToolError) -> JSONResponse:
        return tool_error_response(exc)

    @app.exception_handler(EngineBusy)
    async def _busy(request: Request, exc: EngineBusy) -> JSONResponse:
        # a change the filter task did not take in time (compiling on a first start): 503,
        # nothing applied, and when to try again; it was a 500 and applied later
        return JSONResponse({"detail": str(exc)}, status_code=503, headers={"Retry-After": "10"})
