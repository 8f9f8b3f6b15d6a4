"""GET/PATCH /api/params, POST /api/reset, presets."""

import asyncio
from typing import Any

from fastapi import APIRouter, Body, Depends

from ..engine import Change, Engine, PatchError
from ..models import PATCH_DOC, PATCH_EXAMPLES, Params, PresetRequest
from ..presets import list_presets, load_preset, save_preset
from . import get_engine, unprocessable

router = APIRouter(prefix="/api", tags=["parameters"])
APPLY_TIMEOUT_S = 5.0


async def _apply(engine: Engine, change: Change) -> dict:
    change.done = asyncio.get_running_loop().create_future()
    engine.post(change)
    try:
        return await asyncio.wait_for(change.done, APPLY_TIMEOUT_S)
    except PatchError as e:
        raise unprocessable(e) from None


@router.get("/params", response_model=Params)
async def get_params(engine: Engine = Depends(get_engine)) -> dict:
    """The parameters in effect (SI units)."""
    return engine.params_view()


@router.get("/params/schema")
async def params_schema(engine: Engine = Depends(get_engine)) -> dict:
    """Per estimator: each parameter's unit, range, user unit, choices, help."""
    from ...params import describe
    return {n: describe(type(e.params)) for n, e in engine.estimators.items()}


@router.patch("/params", response_model=Params, description=PATCH_DOC,
              responses={422: {"description": "unknown key or invalid value; nothing applied"}})
async def patch_params(body: dict[str, Any] = Body(..., openapi_examples=PATCH_EXAMPLES),
                       engine: Engine = Depends(get_engine)) -> dict:
    """Change parameters (applied from the next sample)."""
    try:
        change = engine.validate_patch(body)
    except PatchError as e:
        raise unprocessable(e) from None
    return await _apply(engine, change)


@router.post("/reset", response_model=Params)
async def reset(engine: Engine = Depends(get_engine)) -> dict:
    """Forget the orientation of every estimator; they align again."""
    return await _apply(engine, Change(reset=True))


@router.get("/presets")
async def presets(engine: Engine = Depends(get_engine)) -> list[str]:
    """Preset names that can be loaded."""
    return list_presets(engine.settings)


@router.post("/presets/load", response_model=Params)
async def preset_load(req: PresetRequest, engine: Engine = Depends(get_engine)) -> dict:
    """Set every estimator to its defaults plus the preset."""
    try:
        change = load_preset(engine, req.name)
    except PatchError as e:
        raise unprocessable(e) from None
    return await _apply(engine, change)


@router.post("/presets/save")
async def preset_save(req: PresetRequest, engine: Engine = Depends(get_engine)) -> dict:
    """Save the current parameters as a preset."""
    try:
        path = save_preset(engine, req.name)
    except PatchError as e:
        raise unprocessable(e) from None
    return {"saved": str(path)}
