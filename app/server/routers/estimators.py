"""Variants side by side: ``GET /api/estimators``; ``POST /api/estimators {"name", "base",
"params"}`` adds a second instance of an estimator with its own parameters (or
``{"preset": "no-rejection"}``: the primary with every gate off; ``"lab-approx"``: the
lab filter with the approximate time update (2k)); ``DELETE /api/estimators/{name}``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Body, Depends

from app.live.changes import Change, Variant
from app.server.access import require_presenter
from app.server.routers import get_toolkit
from app.server.toolkit import Toolkit
from app.toolkit.errors import ToolError

router = APIRouter(prefix="/api/estimators", tags=["estimators"])


@router.get("")
async def estimators(tk: Toolkit = Depends(get_toolkit)) -> dict:
    return tk.variants.listing()


@router.post("", dependencies=[Depends(require_presenter)])
async def add(body: Any = Body(..., examples=[{"name": "lab-approx", "base": "lab",
                                              "params": {"time_update": "approx"}},
                                             {"preset": "no-rejection"}]),
              tk: Toolkit = Depends(get_toolkit)) -> dict:
    if not isinstance(body, dict):
        raise ToolError("body", "expected a JSON object")
    unknown = set(body) - {"name", "base", "params", "preset"}
    if unknown:
        raise ToolError(sorted(unknown)[0], "unknown key (known: name, base, params, preset)")
    if "preset" in body:
        name, base, params = tk.variants.preset(body["preset"])
        name = body.get("name", name)
    else:
        for k in ("name", "base"):
            if k not in body:
                raise ToolError(k, "required")
        name, base, params = body["name"], body["base"], body.get("params") or {}
        if not isinstance(params, dict):
            raise ToolError("params", "must be an object {param: value}")
    checked = tk.variants.check_add(name, base, params)
    await tk.post(Change(add=[Variant(name, base, checked)]))
    return {"name": name, "base": base, "params": params, **tk.variants.listing()}


@router.delete("/{name}", dependencies=[Depends(require_presenter)])
async def remove(name: str, tk: Toolkit = Depends(get_toolkit)) -> dict:
    await tk.post(Change(remove=[tk.variants.check_remove(name)]))
    return tk.variants.listing()
