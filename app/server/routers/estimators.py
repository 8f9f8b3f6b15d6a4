"""Variants side by side: ``GET /api/estimators``; ``POST /api/estimators {"name", "base",
"params"}`` adds a second instance of an estimator with its own parameters (or
``{"preset": "no-rejection"}``: the primary with every gate off; ``"lab-approx"``: the
lab filter with the approximate time update (2k)); ``DELETE /api/estimators/{name}``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends

from app.server.access import require_presenter
from app.server.lab import LabError, LabTools
from app.server.routers._lab import get_lab, lab_error
from app.server.routers.calibrate import post_change

router = APIRouter(prefix="/api/estimators", tags=["estimators"])


@router.get("")
async def estimators(lab: LabTools = Depends(get_lab)) -> dict:
    b = lab.core.bench
    return {"primary": b.primary, "estimators": [
        {"name": n, "base": b.base_of(n), "builtin": b.base_of(n) == n} for n in b.names]}


@router.post("", dependencies=[Depends(require_presenter)])
async def add(body: Any = Body(..., examples=[{"name": "lab-approx", "base": "lab",
                                              "params": {"time_update": "approx"}},
                                             {"preset": "no-rejection"}]),
              lab: LabTools = Depends(get_lab)) -> dict:
    try:
        if not isinstance(body, dict):
            raise LabError("body", "expected a JSON object")
        unknown = set(body) - {"name", "base", "params", "preset"}
        if unknown:
            raise LabError(sorted(unknown)[0], "unknown key (known: name, base, params, preset)")
        if "preset" in body:
            if body["preset"] == "no-rejection":
                name, base, params = lab.no_rejection()
            elif body["preset"] == "lab-approx":
                name, base, params = "lab-approx", "lab", {"time_update": "approx"}
            else:
                raise LabError("preset", "one of no-rejection, lab-approx")
            name = body.get("name", name)
        else:
            for k in ("name", "base"):
                if k not in body:
                    raise LabError(k, "required")
            name, base, params = body["name"], body["base"], body.get("params") or {}
            if not isinstance(params, dict):
                raise LabError("params", "must be an object {param: value}")
        change = lab.variant_change(name, base, params)
    except LabError as e:
        raise lab_error(e) from None
    await post_change(lab.engine, change)
    return {"name": name, "base": base, "params": params, **(await estimators(lab))}


@router.delete("/{name}", dependencies=[Depends(require_presenter)])
async def remove(name: str, lab: LabTools = Depends(get_lab)) -> dict:
    try:
        change = lab.remove_change(name)
    except LabError as e:
        raise lab_error(e) from None
    await post_change(lab.engine, change)
    return await estimators(lab)
