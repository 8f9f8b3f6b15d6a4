"""``create_app(settings) -> FastAPI``: the dashboard in one process.

The lifespan starts and stops every resource and keeps them on ``app.state`` (no
module-level state): the engine (estimators) and its task, the viser server with the
scene and GUI and their refresh task, the phone TCP server, and the background source
(demo or log replay). A router per concern, in ``app/server/routers/``: ``health``
(/api/health, /api/info), ``state`` (/api/state, /api/stats, WS /ws/state), ``params``
(/api/params, /api/reset, presets), ``phone``, ``push`` (the phone apps' HTTP pushes),
``connect``, ``recordings``, ``calibrate``, ``replay``, ``estimators`` (variants, the
What-if), ``inject``; docs/api.md lists every route. The landing page ``/`` comes from
``static/``.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import textwrap
from pathlib import Path

import viser
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from app.config import load_config
from app.server.engine import Engine
from app.server.access import COOKIE, Access, guard_viewer
from app.server import viser_adapter
from app.server.gui.main import Gui, run_gui
from app.server.limits import BodyLimit, install_error_handlers
from app.server.connect import Connect
from app.server.phones import PUSH_APPS, TICK_S, HttpPhones
from app.sources.phyphox_poll import PhyphoxPoller
from app.server.tcp_phone import SensorFusionServer
from app.sources.slot import PhoneSlot
from app.server.routers import (calibrate, connect, estimators, health, params, phone, push,
                                recordings, replay, state)
from app.server.routers import inject as inject_router
from app.server.gui.toolkit_tab import ToolkitTab, run_toolkit_tab
from app.server.routers import install_tool_errors
from app.server.toolkit import Toolkit
from app.server.gui.scene import Scene, loop_safe_wakeups
from app.server.settings import Settings
from app.server.background import run_demo, run_replay
from app.sources.pacing import ReplayControl
from app.sources.readers import detect_format

log = logging.getLogger("orientlab.server")
STATIC_DIR = Path(__file__).resolve().parents[2] / "static"


async def every(seconds: float, fn) -> None:
    """``fn()`` every ``seconds``, for as long as the lifespan runs: an exception is logged,
    and the task goes on."""
    while True:
        await asyncio.sleep(seconds)
        try:
            fn()
        except Exception:
            log.exception("%s failed", getattr(fn, "__qualname__", fn))


def banner(settings: Settings, lan_ip: str, viewer_port: int, phone_port: int, http_port: int,
           access: Access | None = None, unreachable: str | None = None) -> str:
    """What ``serve`` prints: the links, the phones' addresses (``lan_ip``: the Connect tab's),
    and ``unreachable``, the reason phones cannot push here, if there is one."""
    host = lan_ip if settings.host in ("0.0.0.0", "") else settings.host
    if access is None or access.open:
        page = [f"    open the page:      http://{host}:{http_port}/   (on this PC: http://localhost:{http_port}/)",
                "    access:             --open: anyone on the network may change the session"]
    else:
        page = [f"    presenter's link:   {access.presenter_link(f'http://{host}:{http_port}/')}",
                f"                        (on this PC: {access.presenter_link(f'http://localhost:{http_port}/')})",
                "                        (keep it to yourself: it holds the token that allows changes)",
                f"    students watch at:  http://{host}:{http_port}/   (watch-only)"]
    return "\n".join([
        "",
        "  orientlab is running",
        *page,
        f"    3D viewer only:     http://{host}:{viewer_port}/",
        "    connect a phone (one at a time; the page's Connect tab has QR codes):",
        f"      Sensor Logger:      HTTP push URL  http://{lan_ip}:{http_port}/sensorlogger",
        f"      phyphox:            experiment     http://{lan_ip}:{http_port}/phyphox/orientlab.phyphox",
        f"      Sensor Fusion app:  address {lan_ip}   port {phone_port}   (Stream, 100 Hz)",
        *([textwrap.fill(unreachable, 96, initial_indent="    note:               ",
                         subsequent_indent=" " * 24)] if unreachable else []),
        f"    source:             {settings.source}",
        "  Ctrl-C stops.",
        "",
    ])


def start_source(engine: Engine, settings: Settings, tk: Toolkit | None = None) -> asyncio.Task | None:
    if settings.source == "demo":
        return asyncio.create_task(run_demo(engine, settings.demo_seed), name="demo")
    if settings.source == "none" or settings.phyphox_url is not None:
        engine.pause_background()       # a polled phyphox phone: started by the lifespan
        return None
    path = Path(settings.source)
    control = ReplayControl(path.read_bytes().splitlines(), path.name)
    if tk is not None:  # the page and /api/replay control it
        tk.replay.adopt(control, path.stem)
    return asyncio.create_task(run_replay(engine, path, settings.replay_pause_s, control=control),
                               name="replay")


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    if settings.phyphox_url is not None:
        PhyphoxPoller(settings.phyphox_url, lambda samples, new: None)   # ValueError: exit 2
    elif settings.source not in ("demo", "none"):
        if not Path(settings.source).is_file():
            raise FileNotFoundError(f"--source: no such log file: {settings.source}")
        fmt = detect_format(settings.source)     # ReaderError (a ValueError): exit 2
        if fmt != "applog":   # a CSV or npz replayed as lines was an empty log, looping
            raise ValueError(f"--source: {settings.source} is a {fmt} file; only a Sensor Fusion "
                             "app log is replayed live (`orientlab estimate` reads the others)")
    config = load_config(settings.config)  # read once; a bad preset is refused before anything starts
    access = Access.from_settings(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        st = app.state
        loop = asyncio.get_running_loop()
        engine = Engine(settings, config)
        engine.bind(loop)
        warmup = getattr(app.state, "warmup", None)   # serve: compiling in the background
        if warmup is None:
            await loop.run_in_executor(None, engine.warm_up)
        st.engine = engine
        st.tasks = {}
        with contextlib.redirect_stdout(io.StringIO()):   # viser's own box of its address: the
            # banner says it (the 3D viewer only), beside the page a teacher should open
            st.viewer = viser.ViserServer(host=settings.viewer_bind, port=settings.viewer_port,
                                          label="orientlab", verbose=False)
        try:
            viser_adapter.check(st.viewer)   # every viser internal relied on exists, else a clear error
            loop_safe_wakeups(st.viewer)     # before any viewer connects
            st.scene = Scene(st.viewer)
            st.gui = Gui(st.viewer, engine, st.scene, settings)
            guard_viewer(st.viewer, access)
            engine.pose_listeners.append(st.scene.draw_pose)
            engine.atomic = st.viewer.atomic
            engine.listeners.append(st.scene.draw)
            st.slot = PhoneSlot(settings.phone_idle_s)     # one phone at a time, every app
            st.sensorfusion = SensorFusionServer(engine, settings, st.slot)
            await st.sensorfusion.start()
            st.http_phones = HttpPhones(engine, settings, st.slot)
            st.tasks["phones"] = asyncio.create_task(every(TICK_S, st.http_phones.tick), name="phones")
            st.connect = Connect(settings, st)
            st.lan_ip = st.connect.host()
            if settings.phyphox_url is not None:
                st.http_phones.start_poll(settings.phyphox_url)
            st.tasks["engine"] = asyncio.create_task(engine.run_when_ready(warmup), name="engine")
            st.tasks["quiet"] = asyncio.create_task(every(TICK_S, engine.release_quiet), name="quiet")
            st.tasks["gui"] = asyncio.create_task(run_gui(st.gui, settings.text_hz, settings.plot_hz), name="gui")
            st.toolkit = Toolkit.build(engine, settings, config, st.tasks)   # the lab's tools
            st.gui.injections = st.toolkit.injection.injected_spans   # marked in the Plots panel
            st.gui.background = lambda: (t := st.tasks.get("source")) is not None and not t.done()
            # the Lab tab; the variants' ghosts join the 3D scene
            st.toolkit_tab = ToolkitTab(st.viewer.gui, st.gui.tabs, st.toolkit, loop, server=st.viewer)
            st.tasks["toolkit_tab"] = asyncio.create_task(run_toolkit_tab(st.toolkit_tab), name="toolkit_tab")
            src = start_source(engine, settings, st.toolkit)
            if src is not None:
                st.tasks["source"] = src
            if settings.verbose:
                print(banner(settings, st.lan_ip, st.viewer.get_port(), st.sensorfusion.port,
                             settings.port, access, st.connect.unreachable()), flush=True)
            yield
        finally:
            for t in st.tasks.values():
                t.cancel()
            if getattr(st, "http_phones", None) is not None:
                st.http_phones.stop_poll()
            if getattr(st, "sensorfusion", None) is not None:
                await st.sensorfusion.stop()
            await asyncio.gather(*st.tasks.values(), return_exceptions=True)
            if getattr(st, "toolkit", None) is not None:   # a recording ends cleanly
                st.toolkit.close()
            st.viewer.stop()

    app = FastAPI(title="orientlab", lifespan=lifespan, docs_url=None, redoc_url=None,
                  description="Live orientation estimation from a phone's sensors: state, "
                              "parameters and a WebSocket stream of every estimate.")
    app.state.access = access
    app.state.settings = settings
    install_error_handlers(app)
    push.install_wrong_address_answer(app)
    install_tool_errors(app)       # a tool's refusal (ToolError) as an HTTP answer
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes,
                       paths={a.path: settings.max_push_bytes for a in PUSH_APPS.values()})
    app.include_router(health.router)
    app.include_router(state.router)
    app.include_router(params.router)
    app.include_router(phone.router)
    for r in (recordings, calibrate, replay, estimators, inject_router, push, connect):
        app.include_router(r.router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/docs", include_in_schema=False)
    async def api_docs():
        # Swagger UI from orientlab's own files, not FastAPI's default CDN: a classroom
        # network may have no way out
        sw = "/static/vendor/swagger-ui"
        return get_swagger_ui_html(openapi_url=app.openapi_url, title="orientlab API",
                                   swagger_js_url=f"{sw}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{sw}/swagger-ui.css",
                                   swagger_favicon_url=f"{sw}/favicon-32x32.png")

    @app.get("/", include_in_schema=False)
    async def index(request: Request, token: str | None = None):
        if token is not None and not access.open:
            # the presenter's link: keep the token in a cookie, then show a clean URL
            resp = RedirectResponse("/", status_code=303)
            if access.token_ok(token):
                resp.set_cookie(COOKIE, token, httponly=True, samesite="strict")
            return resp
        # its own agent cluster: Chromium gives the page a process of its own, so the 3D
        # view (the iframe, same site) cannot hold up the live plots' redraws
        return FileResponse(STATIC_DIR / "index.html", headers={"Origin-Agent-Cluster": "?1"})

    return app
