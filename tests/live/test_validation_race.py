"""Validation on other threads never races a variant being added or removed.

viser runs the GUI's callbacks on its own thread pool, and those validate a change
(:meth:`LiveCore.validate`) while the filter task may be adding or removing a variant
(the Estimators tab, ``POST /api/estimators``). The first version validated against the
live ensemble: a variant removed half-way through a validation raised ``KeyError`` (not a
refusal), and a change validated against one ``v1`` was applied to another (removed and
added again meanwhile) or reported applied when its instance was gone.

Here: the real :class:`~app.server.engine.Engine` with its filter task on an event loop
in a thread; one thread adds and removes the variant ``v1`` through ``Engine.post`` (what
the variant API does); several threads validate changes naming it and post them the
way the API and the GUI do. Every outcome must be a change applied to exactly the
instance it was validated against, or a :class:`PatchError`; never anything else.
"""

from __future__ import annotations

import asyncio
import itertools
import sys
import threading
import time
import traceback
from collections import Counter

import pytest

from app.live.changes import Change, PatchError, Variant
from app.server.engine import Engine
from app.server.settings import Settings

RUN_S = 3.0
# one parameter of the lab estimator per validating thread: only that thread sets it,
# so after its change is applied the instance it validated against must hold its value
OWN_FIELDS = ("mag_std", "gyr_std", "acc_std")


@pytest.fixture
def engine():
    eng = Engine(Settings(source="none"))
    loop = asyncio.new_event_loop()
    eng.bind(loop)
    th = threading.Thread(target=loop.run_forever, name="filter-loop", daemon=True)
    th.start()
    task = asyncio.run_coroutine_threadsafe(eng.run(), loop)
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)      # switch threads often: the races show within seconds
    try:
        yield eng
    finally:
        sys.setswitchinterval(old)
        task.cancel()
        time.sleep(0.05)
        loop.call_soon_threadsafe(loop.stop)
        th.join(5.0)
        loop.close()


def post(eng: Engine, change: Change, timeout: float = 10.0) -> dict:
    """Post a change as the API does (Engine.post with a future of the engine's loop);
    the new parameters, or PatchError."""
    async def submit():
        done = asyncio.get_running_loop().create_future()
        eng.post(change, done)
        return await done
    return asyncio.run_coroutine_threadsafe(submit(), eng.loop).result(timeout)


def test_validation_and_apply_never_race_variant_add_remove(engine):
    eng = engine
    ensemble = eng.core.ensemble
    stop = threading.Event()
    errors: list[str] = []
    wrong: list[str] = []
    counts: Counter = Counter()
    lock = threading.Lock()
    marker = itertools.count(1)

    def note(key: str) -> None:
        with lock:
            counts[key] += 1

    def fail(where: str) -> None:
        with lock:
            if len(errors) < 20:
                errors.append(f"{where}:\n{traceback.format_exc()}")

    def mutator():
        k = 0
        while not stop.is_set():
            k += 1
            try:
                post(eng, Change(add=[Variant("v1", "lab", {"p0": 0.1 + (k % 7) * 0.01})]))
                note("added")
                post(eng, Change(remove=["v1"]))
                note("removed")
            except PatchError:
                note("mutator refused")
            except Exception:
                fail("add/remove")

    def validator(i: int):
        own = OWN_FIELDS[i]
        while not stop.is_set():
            value = 0.5 + next(marker) * 1e-7     # a value no other change sets
            before = ensemble.instances.get("v1")
            try:
                change = eng.core.validate({"estimators": {"v1": {own: value}}})
            except PatchError:
                note("refused by validation")     # v1 not on the ensemble: fine
                continue
            except Exception:
                fail(f"validate (thread {i})")
                continue
            after = ensemble.instances.get("v1")
            try:
                view = post(eng, change)
            except PatchError:
                note("refused at apply")          # raced with add/remove: nothing applied
                continue
            except Exception:
                fail(f"apply (thread {i})")
                continue
            note("applied")
            if view["estimators"].get("v1", {}).get(own) != value:
                wrong.append(f"{own}={value} reported applied; v1 now "
                             f"{view['estimators'].get('v1', {}).get(own)!r}")
            if before is not None and before is after and getattr(before.estimator.params, own) != value:
                wrong.append(f"{own}={value} validated against one v1 and reported applied, but that v1 did not get it")

    def shared_and_primary():
        while not stop.is_set():
            for body in ({"primary": "v1"}, {"use_mag": True},
                         {"estimators": {"v1": {"use_acc": True}, "lab": {"use_acc": True}}},
                         {"primary": "robust"}):
                try:
                    change = eng.core.validate(body)
                except PatchError:
                    note("refused by validation")
                    continue
                except Exception:
                    fail(f"validate {body}")
                    continue
                try:
                    view = post(eng, change)
                except PatchError:
                    note("refused at apply")
                    continue
                except Exception:
                    fail(f"apply {body}")
                    continue
                note("applied")
                if "primary" in body and view["primary"] != body["primary"]:
                    wrong.append(f"{body} reported applied; the primary is {view['primary']}")

    threads = [threading.Thread(target=mutator, name="mutator")]
    threads += [threading.Thread(target=validator, args=(i,), name=f"validator-{i}")
                for i in range(len(OWN_FIELDS))]
    threads.append(threading.Thread(target=shared_and_primary, name="shared"))
    for t in threads:
        t.start()
    deadline = time.monotonic() + RUN_S
    while time.monotonic() < deadline and not errors and not wrong:
        time.sleep(0.05)
    stop.set()
    for t in threads:
        t.join(15.0)
    assert not any(t.is_alive() for t in threads), "a thread hung"
    assert not errors, f"{len(errors)} failures other than PatchError; first:\n{errors[0]}"
    assert not wrong, wrong[:5]
    # the race was really run: variants came and went, changes landed and were refused
    assert counts["added"] > 20 and counts["removed"] > 20, counts
    assert counts["applied"] > 20, counts
    assert counts["refused by validation"] + counts["refused at apply"] > 0, counts
    assert counts["mutator refused"] == 0, counts
