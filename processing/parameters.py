"""Parameter classes of the processing stages: frozen pydantic dataclasses, checked when they are built.

:func:`parameters` turns a plain class body (fields with defaults, ``pydantic.Field`` constraints, an optional
``model_validator`` for checks across fields) into a frozen pydantic dataclass that forbids unknown fields and
non-finite numbers. It stays a dataclass (``dataclasses.replace`` and attribute access work as before) and nests
in pydantic models (a protocol's ``analysis.options``), where errors carry the field's path and the file's line.
Built directly, a bad value raises :class:`~skinstretch.processing.errors.InvalidInputError` naming the class and
the field, one line per problem.
"""

from __future__ import annotations

import functools
from typing import TypeVar

from pydantic import ConfigDict, ValidationError
from pydantic.dataclasses import dataclass as _pydantic_dataclass

from skinstretch.processing.errors import InvalidInputError

__all__ = ["parameters", "PARAMETERS_CONFIG", "describe_validation_error"]

#: Unknown fields are errors (a misspelt option must not be silently ignored); NaN and inf are never parameters.
PARAMETERS_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False)

_C = TypeVar("_C", bound=type)


def describe_validation_error(exc: ValidationError, prefix: str = "") -> str:
    """``prefix.field: message`` for every problem of a pydantic error, joined by "; "."""
    parts = []
    for err in exc.errors(include_url=False):
        loc = ".".join(str(p) for p in err.get("loc", ()))
        where = ".".join(p for p in (prefix, loc) if p)
        parts.append(f"{where}: {err['msg']}" if where else err["msg"])
    return "; ".join(parts)


def parameters(cls: _C) -> _C:
    """Make ``cls`` a frozen, validated parameter dataclass (see the module docstring)."""
    cls = _pydantic_dataclass(cls, frozen=True, config=PARAMETERS_CONFIG)
    validated_init = cls.__init__

    @functools.wraps(validated_init)
    def __init__(self, *args, **kwargs) -> None:
        try:
            validated_init(self, *args, **kwargs)
        except ValidationError as exc:
            raise InvalidInputError(describe_validation_error(exc, cls.__name__)) from None

    cls.__init__ = __init__
    return cls
