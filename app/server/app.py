"""``create_app(settings) -> FastAPI``: the dashboard in one process.

The lifespan starts and stops every resource and keeps them on ``app.state`` (no
module-level state): the engine (estimators) and its task, the viser server with the
scene and GUI and their refresh task, the phone TCP server, and the background source
(demo or log replay). Routers: ``health`` (/api/health, /api/info), ``state``
(/api/state, /api/stats, WS /ws/state), ``params`` (/api/params, /api/reset, presets);
the landing page ``/`` comes from ``static/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from pathlib import Path

import viser
from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from ..config import load_config
from .engine import Engine
from .gui import Gui, run_gui
from .net import lan_ipv4
from .receiver import PhoneServer
from .routers import health, params, state
from .scene import Scene
from .settings import Settings
from .sources import run_demo, run_replay

log = logging.getLogger("orientlab.server")
STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


def banner(settings: Settings, lan_ip: str, viewer_port: int, phone_port: int, http_port: int) -> str:
    host = lan_ip if settings.host in ("0.0.0.0", "") else settings.host
    return "\n".join([
        "",
        "  orientlab is running",
        f"    open the page:      http://{host}:{http_port}/   (on this PC: http://localhost:{http_port}/)",
        f"    3D viewer only:     http://{host}:{viewer_port}/",
        f"    phone app address:  {lan_ip}   port {phone_port}   (Sensor Fusion app: Stream, 100 Hz)",
        f"    source:             {settings.source}",
        "  Ctrl-C stops.",
        "",
    ])


def start_source(engine: Engine, settings: Settings) -> asyncio.Task | None:
    if settings.source == "demo":
        return asyncio.create_task(run_demo(engine, settings.demo_seed), name="demo")
    if settings.source == "none":
        engine.pause_background()
        return None
    return asyncio.create_task(run_replay(engine, settings.source, settings.replay_pause_s),
                               name="replay")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    if settings.source not in ("demo", "none") and not Path(settings.source).is_file():
        raise FileNotFoundError(f"--source: no such log file: {settings.source}")
    load_config(settings.config)  # a bad preset is refused before anything starts

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        st = app.state
        loop = asyncio.get_running_loop()
        engine = Engine(settings)
        engine.bind(loop)
        await loop.run_in_executor(None, engine.warm_up)
        st.engine = engine
        st.tasks = {}
        st.viewer = viser.ViserServer(host=settings.viewer_bind, port=settings.viewer_port,
                                      label="orientlab", verbose=False)
        try:
            st.scene = Scene(st.viewer)
            st.gui = Gui(st.viewer, engine, st.scene, settings)
            engine.pose_listeners.append(st.scene.draw_pose)
            engine.listeners.append(st.scene.draw)
            st.phone = PhoneServer(engine, settings)
            await st.phone.start()
            st.lan_ip = lan_ipv4()
            st.tasks["engine"] = asyncio.create_task(engine.run(), name="engine")
            st.tasks["gui"] = asyncio.create_task(run_gui(st.gui, settings.plot_hz), name="gui")
            src = start_source(engine, settings)
            if src is not None:
                st.tasks["source"] = src
            if settings.verbose:
                print(banner(settings, st.lan_ip, st.viewer.get_port(), st.phone.port,
                             settings.port), flush=True)
            yield
        finally:
            for t in st.tasks.values():
                t.cancel()
            if getattr(st, "phone", None) is not None:
                await st.phone.stop()
            await asyncio.gather(*st.tasks.values(), return_exceptions=True)
            st.viewer.stop()

    app = FastAPI(title="orientlab", lifespan=lifespan,
                  description="Live orientation estimation from a phone's sensors: state, "
                              "parameters and a WebSocket stream of every estimate.")
    app.include_router(health.router)
    app.include_router(state.router)
    app.include_router(params.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    return app
