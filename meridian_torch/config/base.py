"""The base of every config model: strict, frozen, finite."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

__all__ = ["StrictModel"]


class StrictModel(BaseModel):
    """Unknown keys are errors; instances are frozen (change them with `model_copy(update=...)`,
    which does not re-validate); NaN and infinities are refused in every float (an infinite sigma
    or gate silently disables what it bounds)."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False)
