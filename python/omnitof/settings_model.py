"""The base of every settings model that users write (configurations, worlds, experiments)."""

from __future__ import annotations

import types
import typing
from typing import Any

from pydantic import BaseModel, model_validator


def _numeric(annotation: Any) -> bool:
    """Whether a field holds an int or a float (possibly optional), and never a bool."""
    if annotation in (int, float):
        return True
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        return bool not in args and any(a in (int, float) for a in args)
    return False


class SettingsModel(BaseModel):
    """Refuses a YAML boolean for a number: pydantic reads `resolution: true` as 1.0 and
    `particles: yes` as 1, where the user wrote a value into the wrong field or meant another.
    A model check, not a field check: pydantic allows no field check on a union's discriminator."""

    @model_validator(mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                field = cls.model_fields.get(name) if isinstance(name, str) else None
                if isinstance(value, bool) and field is not None and _numeric(field.annotation):
                    raise ValueError(f"{name} expects a number, got the boolean {str(value).lower()}")
        return data
