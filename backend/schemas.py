"""The base of every request body: what the API refuses before a handler sees it."""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict


class StrictRequest(BaseModel):
    """NaN and ±Infinity are refused in every number field (JSON as Python parses it accepts
    them, and `Infinity` passes a `gt=0` bound), with a 422 naming the field; so is a field the
    request does not have (a misspelt option would otherwise be dropped without a word)."""

    model_config = ConfigDict(allow_inf_nan=False, extra="forbid")


def finite_json(value):
    """`value` with non-finite floats written as strings, so that a validation error that
    quotes the offending input can still be sent as JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(v) for v in value]
    return value
