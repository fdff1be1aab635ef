"""FastAPI dependencies."""
from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from service.model.body import BodyModel, load_body_model
from service.settings import Settings, get_settings


async def get_app_settings(request: Request) -> Settings:
    """This app's settings (``create_app(settings)`` stores them in ``app.state``). Async and
    override-free on purpose: a sync or overridden dependency costs a thread-pool hop or a
    signature analysis on every request."""
    settings = getattr(request.app.state, "settings", None)
    return settings if settings is not None else get_settings()


async def get_body_model(request: Request, settings: Annotated[Settings, Depends(get_app_settings)]) -> BodyModel:
    """The body model loaded once at startup (``app.state.body_model``); without a lifespan
    (e.g. an in-process test client) the process-wide cached model for ``settings``."""
    model = getattr(request.app.state, "body_model", None)
    if model is None:
        path = str(settings.body_model_path) if settings.body_model_path else None
        model = load_body_model(path)
    return model


SettingsDep = Annotated[Settings, Depends(get_app_settings)]
"""Route parameter type for the settings of the app serving the request."""
