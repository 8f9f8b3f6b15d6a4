"""GET /api/health and /api/info."""

from fastapi import APIRouter, Depends, Request

from app.server.engine import Engine
from app.server.models import Health, Info
from app.server.routers import get_engine

router = APIRouter(prefix="/api", tags=["health"])


@router.get("/health", response_model=Health)
async def health(request: Request, engine: Engine = Depends(get_engine)) -> Health:
    """Is the filter task running, and which filters are ready (``orientlab serve``
    compiles them in the background: the page answers meanwhile)?"""
    h = engine.health(request.app.state.tasks.get("engine"))
    warmup = getattr(request.app.state, "warmup", None)
    names = engine.core.ensemble.names
    filters = warmup.status() if warmup is not None else dict.fromkeys(names, "ready")
    return Health(**h, source=engine.core.source_kind(), estimators=names,
                  primary=engine.core.ensemble.primary, filters=filters,
                  ready=warmup is None or warmup.ready)


@router.get("/info", response_model=Info)
async def info(request: Request, engine: Engine = Depends(get_engine)) -> Info:
    """The viewer's port; for the presenter also the phone port and the PC's LAN address
    (for the landing page)."""
    st = request.app.state
    presenter = st.access.is_presenter(request)
    return Info(viewer_port=st.viewer.get_port(),
                phone_port=st.sensorfusion.port if presenter else None,
                lan_ip=st.connect.host(request) if presenter else None,
                source=engine.core.source_kind(), presenter=presenter,
                viewer_token=st.access.token if presenter and not st.access.open else None)
