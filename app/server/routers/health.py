"""GET /api/health and /api/info."""

from fastapi import APIRouter, Depends, Request

from ..engine import Engine
from ..models import Health, Info
from . import get_engine

router = APIRouter(prefix="/api", tags=["health"])


@router.get("/health", response_model=Health)
async def health(request: Request, engine: Engine = Depends(get_engine)) -> Health:
    """Is the filter task running?"""
    task = request.app.state.tasks.get("engine")
    ok = task is not None and not task.done()
    return Health(status="ok" if ok else "stopped", source=engine.source_kind(),
                  estimators=list(engine.estimators), primary=engine.primary)


@router.get("/info", response_model=Info)
async def info(request: Request, engine: Engine = Depends(get_engine)) -> Info:
    """Ports and the PC's LAN address (for the landing page)."""
    st = request.app.state
    return Info(viewer_port=st.viewer.get_port(), phone_port=st.phone.port, lan_ip=st.lan_ip,
                source=engine.source_kind())
