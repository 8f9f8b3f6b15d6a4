"""GET/PATCH /api/params, POST /api/reset, presets."""

from typing import Any

from fastapi import APIRouter, Body, Depends, HTTPException, Request

from app.server.access import require_presenter
from app.server.engine import Change, Engine, PatchError
from app.server.models import PATCH_DOC, PATCH_EXAMPLES, Params, PresetRequest
from app.server.presets import (MAX_PRESET_BYTES, PresetWriteError, list_presets, load_preset,
                                load_preset_path, load_preset_text, save_preset, save_preset_text)
from app.server.routers import get_engine, unprocessable

router = APIRouter(prefix="/api", tags=["parameters"])
APPLY_TIMEOUT_S = 5.0


async def _apply(engine: Engine, change: Change) -> dict:
    """The parameters in force after ``change``; with ``warnings`` when loading its preset
    said something (a key read as its new name, a removed one left out)."""
    try:
        view = await engine.apply(change, APPLY_TIMEOUT_S)
        return {**view, "warnings": list(change.notes)} if change.notes else view
    except PatchError as e:
        raise unprocessable(e) from None


def refused(e: PatchError) -> HTTPException:
    """A refused change or preset: 422 naming the field; 507 (with the reason) when the
    preset folder refused the write (:class:`PresetWriteError`)."""
    exc = unprocessable(e)
    if isinstance(e, PresetWriteError):
        exc.status_code = e.status
    return exc


@router.get("/params", response_model=Params)
async def get_params(engine: Engine = Depends(get_engine)) -> dict:
    """The parameters in effect (SI units)."""
    return engine.core.params_view()


@router.get("/params/schema")
async def params_schema(engine: Engine = Depends(get_engine)) -> dict:
    """Per estimator: each parameter's unit, range, user unit, choices, help."""
    return engine.core.params_schema()


@router.patch("/params", response_model=Params, description=PATCH_DOC, dependencies=[Depends(require_presenter)],
              responses={422: {"description": "unknown key or invalid value; nothing applied"}})
async def patch_params(body: dict[str, Any] = Body(..., openapi_examples=PATCH_EXAMPLES),
                       engine: Engine = Depends(get_engine)) -> dict:
    """Change parameters (applied from the next sample)."""
    try:
        change = engine.core.validate(body)
    except PatchError as e:
        raise unprocessable(e) from None
    return await _apply(engine, change)


@router.post("/reset", response_model=Params, dependencies=[Depends(require_presenter)])
async def reset(engine: Engine = Depends(get_engine)) -> dict:
    """Forget the orientation of every estimator; they align again."""
    return await _apply(engine, Change(reset=True))


@router.get("/presets")
async def presets(engine: Engine = Depends(get_engine)) -> list[str]:
    """Preset names that can be loaded."""
    return list_presets(engine.settings)


@router.post("/presets/load", response_model=Params, dependencies=[Depends(require_presenter)])
async def preset_load(req: PresetRequest, engine: Engine = Depends(get_engine)) -> dict:
    """Set every estimator to its defaults plus the preset: ``{"name": ...}`` (saved or
    shipped) or ``{"path": ...}`` (a preset file on this PC, e.g. written by
    ``orientlab calibrate``)."""
    try:
        if req.path is not None:
            change = load_preset_path(engine, req.path)
        else:
            change = load_preset(engine, req.name)
    except PatchError as e:
        raise unprocessable(e) from None
    return await _apply(engine, change)


@router.post("/presets/save", dependencies=[Depends(require_presenter)])
async def preset_save(req: PresetRequest, engine: Engine = Depends(get_engine)) -> dict:
    """Save the current parameters as a preset (in the user's preset folder)."""
    try:
        path = save_preset(engine, req.name)
    except PatchError as e:     # a refused name (422) or the folder refused the write (507)
        raise refused(e) from None
    return {"saved": str(path)}


@router.post("/presets/upload", response_model=Params, dependencies=[Depends(require_presenter)],
             openapi_extra={"requestBody": {"content": {"application/toml": {"schema": {"type": "string"}}},
                                            "required": True}})
async def preset_upload(request: Request, name: str | None = None,
                        engine: Engine = Depends(get_engine)) -> dict:
    """Load a preset sent as the request body (the TOML text of a preset file, at most
    64 KB); with ``?name=...`` also keep it in the user's preset folder."""
    text = await request.body()
    try:
        if len(text) > MAX_PRESET_BYTES:
            raise PatchError(("file",), f"larger than {MAX_PRESET_BYTES // 1024} KB: not a preset")
        change = load_preset_text(engine, text)
        if name is not None:
            save_preset_text(engine.settings, name, text)
    except PatchError as e:     # a refused name (422) or the folder refused the write (507)
        raise refused(e) from None
    return await _apply(engine, change)
