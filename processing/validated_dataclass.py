"""Frozen value objects whose fields pydantic validates, with errors that name the class, the field and the value.

``@validated_dataclass`` is :func:`pydantic.dataclasses.dataclass` (frozen; any Python type allowed as a field) whose
validation errors are re-raised as one :class:`~skinstretch.processing.errors.InvalidInputError`, so the command line
reports them in one line like every other error of ours, e.g.
``field_width_mm should be greater than 0, got -1.0 (PrismOptics)``. Constraints that involve several fields go in a
``@pydantic.model_validator(mode="after")`` method raising InvalidInputError; its message is kept as it is.
The instances are ordinary frozen dataclasses: ``dataclasses.replace`` validates the new values again.

The field types below say the usual constraints once (finite floats; positive, non-negative, probabilities); they
take Python and numpy numbers, not text (pydantic alone would read ``"62"`` as 62.0).
"""

from __future__ import annotations

import functools
import math
import numbers
from typing import Annotated, Any, Callable, TypeVar

from pydantic import BeforeValidator, ConfigDict, Field, ValidationError
from pydantic.dataclasses import dataclass as _pydantic_dataclass
from pydantic_core import PydanticCustomError

from skinstretch.processing.errors import InvalidInputError, SkinstretchError

__all__ = [
    "FiniteFloat",
    "Float",
    "NonNegativeFloat",
    "NonNegativeInt",
    "PositiveFloat",
    "PositiveInt",
    "Probability",
    "validated_dataclass",
]



def _not_text(value: Any) -> Any:
    if isinstance(value, (str, bytes, bool)):
        raise PydanticCustomError("number_type", "Input should be a number")
    return value


def _not_nan(value: Any) -> Any:
    """A number that is not NaN, said before any bound is tested (NaN fails every bound: "nan should be less than
    80" would be the message)."""
    value = _not_text(value)
    if isinstance(value, numbers.Real) and math.isnan(value):
        raise PydanticCustomError("finite_number", "Input should be a number, not NaN")
    return value


def _finite(value: Any) -> Any:
    value = _not_text(value)
    if isinstance(value, numbers.Real) and not math.isfinite(value):
        raise PydanticCustomError("finite_number", "Input should be a finite number")
    return value


_Number = BeforeValidator(_not_text)
_NotNaN = BeforeValidator(_not_nan)
_Finite = BeforeValidator(_finite)
#: Any number but NaN (infinity allowed, e.g. a camera that never answers).
Float = Annotated[float, _NotNaN]
FiniteFloat = Annotated[float, _Finite, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, _Finite, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, _Finite, Field(ge=0, allow_inf_nan=False)]
#: A probability of an event that must not be certain: [0, 1).
Probability = Annotated[float, _Finite, Field(ge=0, lt=1)]
PositiveInt = Annotated[int, _Number, Field(gt=0)]
NonNegativeInt = Annotated[int, _Number, Field(ge=0)]

_CONFIG = ConfigDict(arbitrary_types_allowed=True)
_T = TypeVar("_T")


def _one_line(cls: type, exc: ValidationError) -> str | SkinstretchError:
    """The message of a validation error, or the project error a validator raised (returned to be re-raised)."""
    names = list(cls.__dataclass_fields__)
    parts = []
    for err in exc.errors(include_url=False):
        original = (err.get("ctx") or {}).get("error")
        if isinstance(original, SkinstretchError):
            return original
        loc = list(err.get("loc", ()))
        if loc and isinstance(loc[0], int) and loc[0] < len(names):  # a positional argument
            loc[0] = names[loc[0]]
        name = ".".join(str(p) for p in loc) or "arguments"
        msg = str(err["msg"])
        msg = msg[len("Input "):] if msg.startswith("Input ") else msg.removeprefix("Value error, ")
        if "input" in err and not isinstance(err["input"], dict):
            msg += f" (got {err['input']!r})" if ", got " in msg else f", got {err['input']!r}"
        parts.append(f"{name} {msg}")
    # The field opens the message (the house style, which the command line turns into the flag's name).
    return "; ".join(parts) + f" ({cls.__name__})"


def validated_dataclass(cls: type[_T] | None = None, *, frozen: bool = True) -> Any:
    """Class decorator: a pydantic-validated dataclass (frozen by default) raising InvalidInputError."""

    def wrap(klass: type[_T]) -> type[_T]:
        klass = _pydantic_dataclass(frozen=frozen, config=_CONFIG)(klass)
        validating_init: Callable[..., None] = klass.__init__

        @functools.wraps(validating_init)
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            try:
                validating_init(self, *args, **kwargs)
            except ValidationError as exc:
                error = _one_line(type(self), exc)
                if isinstance(error, SkinstretchError):
                    raise error from None
                raise InvalidInputError(error) from None

        klass.__init__ = __init__  # type: ignore[method-assign]
        return klass

    return wrap if cls is None else wrap(cls)
