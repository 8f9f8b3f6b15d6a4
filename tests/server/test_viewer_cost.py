"""What a viewer receives, read as a browser tab reads it: a real viser WebSocket client
on the real server's viewer port, its messages decoded (zstd, then msgpack).

- at the default view (the demo, nothing started in the Lab tab) the Lab tab's heading
  plot sends nothing (the server cannot know whether a browser shows that tab), while
  the dashboard's own plots do arrive, as two ends for a gate's constant line;
- once a variant runs beside the builtins, the heading plot follows the stream.
"""

from __future__ import annotations

import asyncio
import threading
from collections import Counter

import httpx
import msgspec
import pytest
import viser
import websockets
import zstandard

from harness import running_server, wait_for


class ViewerClient:
    """A viser client in a thread: counts the ``data`` updates per GUI handle uuid and
    keeps the last data sent to each."""

    def __init__(self, port: int):
        self.url = f"ws://127.0.0.1:{port}"
        self.updates: Counter = Counter()
        self.last: dict[str, object] = {}
        self.messages = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    def __enter__(self) -> "ViewerClient":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(10)

    def count(self, uuid: str) -> int:
        with self._lock:
            return self.updates[uuid]

    async def _run(self) -> None:
        dz = zstandard.ZstdDecompressor()
        async with websockets.connect(self.url, max_size=None,
                                      subprotocols=[f"viser-v{viser.__version__}"]) as ws:
            while not self._stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 0.5)
                except asyncio.TimeoutError:
                    continue
                n_inner = int.from_bytes(raw[:8], "little")
                n_comp = int.from_bytes(raw[8:16], "little")
                inner = dz.decompress(raw[16:16 + n_comp], max_output_size=n_inner)
                for m in msgspec.msgpack.decode(inner)["messages"]:
                    with self._lock:
                        self.messages += 1
                        if m.get("type") == "GuiUpdateMessage" and "data" in m["updates"]:
                            self.updates[m["uuid"]] += 1
                            self.last[m["uuid"]] = m["updates"]["data"]


def test_hidden_lab_heading_plot_sends_nothing_until_a_variant_runs(tmp_path):
    with running_server(source="demo", preset_dir=tmp_path) as srv, \
            httpx.Client(base_url=srv.url, timeout=30.0) as api:
        gui, toolkit_tab = srv.app.state.gui, srv.app.state.toolkit_tab
        monitor = toolkit_tab.p_monitor._impl.uuid
        acc_plot = gui.p_acc.handle._impl.uuid
        nis_plot = gui.p_nis.handle._impl.uuid
        with ViewerClient(srv.viewer_port) as viewer:
            # the dashboard's plots arrive (so this client does read the updates) ...
            wait_for(lambda: viewer.count(acc_plot) >= 4, 60.0, what="|acc| plot updates")
            # ... the heading plot of the Lab tab does not
            assert viewer.count(monitor) == 0
            assert not toolkit_tab.monitor_live()
            # a gate's line: its two ends, gaps between (the series spans them); robust,
            # the demo's primary, has both NIS gates once it makes updates

            def last_nis():
                with viewer._lock:
                    data = viewer.last.get(nis_plot)
                return data if data is not None and data[3][0] is not None else None
            x, nis_a, nis_m, gate_a, gate_m = wait_for(last_nis, 30.0, what="the NIS gates")
            assert sum(v is not None for v in nis_a) > 10
            for gate, name in ((gate_a, "acc_nis_gate"), (gate_m, "mag_nis_gate")):
                assert gate[1:-1] == [None] * (len(gate) - 2)
                assert gate[0] == gate[-1] == pytest.approx(
                    getattr(gui.engine.core.ensemble.params_of("robust"), name), rel=1e-3)
            # a variant beside the builtins: the heading plot follows the stream
            r = api.post("/api/estimators", json={"preset": "no-rejection"})
            assert r.status_code == 200, r.text
            wait_for(lambda: viewer.count(monitor) >= 2, 30.0, what="heading plot updates")
            with viewer._lock:
                data = viewer.last[monitor]
            assert len(data[0]) <= 300 and len(data) == len(toolkit_tab.p_monitor.series)
