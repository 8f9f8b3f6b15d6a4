"""POST /api/recordings/{name}/rerun on a real server (issue 21, item 4): the change the
page is pre-filled with shows on the demo and on a real log, and the answer carries the
live filters' error over the same rows and what the error is measured against."""

from __future__ import annotations

import shutil

import httpx
import pytest

from app.toolkit.whatif import first_suggestion
from harness import running_server
from toolkit.test_whatif_first_try import VISIBLE_DEG, WALK, demo_recording


def test_the_first_suggestion_through_the_api_on_the_demo_and_a_real_log(tmp_path, shared_dir):
    rec = tmp_path / "rec"
    rec.mkdir()
    core, _ = demo_recording(rec, "demo", warm_s=38.0, seconds=38.0)
    shutil.copy(shared_dir / "data" / "sensorfusion-app" / WALK, rec / "walk.txt")
    with running_server(source="none", preset_dir=tmp_path, recordings=rec) as srv, \
            httpx.Client(base_url=srv.url, timeout=120.0) as api:
        tk = srv.app.state.toolkit
        est, param, value = first_suggestion(tk.whatif.specs(), tk.engine.core.ensemble.primary)
        patch = {est: {param: value}}
        r = api.post("/api/recordings/demo/rerun", json={"patch": patch})
        assert r.status_code == 200, r.text
        w = r.json()
        e = w["estimators"][est]
        key = "error_to_truth_deg"
        assert w["reference"] == "truth" and "truth" in w["notes"][0]
        assert abs(e["after"][key]["rms"] - e["before"][key]["rms"]) >= VISIBLE_DEG
        assert e["live"][key]["rms"] == pytest.approx(e["before"][key]["rms"], abs=0.5)
        r = api.post("/api/recordings/walk/rerun", json={"patch": patch})
        assert r.status_code == 200, r.text
        w = r.json()
        assert w["reference"] is None and "no reference" in w["notes"][0]
        assert w["estimators"][est]["change_deg"]["rms"] >= VISIBLE_DEG
