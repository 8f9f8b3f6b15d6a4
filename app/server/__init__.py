"""The live dashboard: ``orientlab serve``.

Data flow (one process, one asyncio loop for FastAPI/uvicorn and the filter)::

    phone TCP stream ─┐
    demo / log replay ┴─> Session (line splitter, parse_line, SampleOrderer)
        -> Engine task (every estimator steps on every sample; one is primary)
        -> snapshot -> viser scene (scene.py), GUI read-outs and plots (gui.py),
                       HTTP/WebSocket API (routers/)

``create_app(settings)`` in :mod:`app.server.app` builds it; :func:`app.server.run.serve`
runs it.
"""
