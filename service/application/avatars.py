"""Avatars that are not stored: from measurements (``POST /v1/avatars``), and the template."""
from __future__ import annotations

from typing import Any

from service.model.body.model import BodyModel
from service.model.body.shape import AvatarFit, MeasurementError, avatar_from_measurements

from . import scenes
from .errors import Invalid


def from_measurements(model: BodyModel, measurements: dict[str, Any]) -> AvatarFit:
    """Any subset of the 12 attributes -> the avatar (422 naming the attribute otherwise)."""
    try:
        return avatar_from_measurements(model, measurements)
    except MeasurementError as exc:
        raise Invalid(("body", "measurements", str(exc.field)), exc.message) from exc


def template_obj(model: BodyModel) -> str:
    return scenes.obj_text(model.body_vertices(model.mean), model.body_faces,
                           "tryon body template: mean avatar body surface, metres, Y up, facing +Z")
