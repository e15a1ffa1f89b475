"""YAML configuration files (protocols, rigs, scenes, analysis parameters) validated by pydantic models.

Files are composed with their line numbers kept (``yaml.compose``), so every error is one line per problem naming
the file, the line and the field, e.g. ``protocol.yaml:12: trials[1].duration_s: Input should be greater than 0``.
Every layer that reads a configuration file uses :func:`parse_yaml_model`; it imports nothing of skinstretch's layers
but the root error type, so processing, simulators and experiments can all use it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from skinstretch.processing.errors import ConfigError

__all__ = ["parse_yaml_model", "read_config_text", "validation_messages"]

_M = TypeVar("_M", bound=BaseModel)
def _node_lines(node: yaml.Node, path: tuple = (), out: dict | None = None) -> dict[tuple, int]:
    """Map every key path of a composed YAML document to its (1-based) line number."""
    out = {} if out is None else out
    out[path] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            key = key_node.value
            _node_lines(value_node, path + (key,), out)
            # The key's line, not the value's: a nested block value starts on the next line.
            out[path + (key,)] = key_node.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _node_lines(item, path + (i,), out)
    return out


def _format_loc(loc: tuple) -> str:
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + str(part)
    return text or "(document)"


def _line_for(loc: tuple, lines: dict[tuple, int]) -> int:
    # pydantic locations may carry validator names that are not YAML keys; fall back to the longest known prefix.
    loc = tuple(p for p in loc if isinstance(p, int) or not str(p).startswith("function-"))
    for k in range(len(loc), -1, -1):
        if loc[:k] in lines:
            return lines[loc[:k]]
    return 1


def validation_messages(exc: ValidationError, *, source: str, lines: dict[tuple, int] | None = None) -> str:
    """One line per problem of a pydantic error: ``source:line: field: message`` (no line when unknown)."""
    messages = []
    for err in exc.errors(include_url=False):
        loc = tuple(err.get("loc", ()))
        where = f"{source}:{_line_for(loc, lines)}" if lines else source
        messages.append(f"{where}: {_format_loc(loc)}: {err['msg']}")
    return "\n".join(messages)


def parse_yaml_model(model: type[_M], text: str, *, source: str, empty_ok: bool = False) -> _M:
    """Validate YAML ``text`` as ``model``; ConfigError names ``source``, the line and the field of every problem.

    ``empty_ok``: an empty document is the model's defaults (otherwise an error).
    """
    try:
        node = yaml.compose(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{where}: not valid YAML ({problem})") from None
    if node is None and not empty_ok:
        raise ConfigError(f"{source}:1: the file is empty")
    if node is not None and not isinstance(node, yaml.MappingNode):
        raise ConfigError(f"{source}:{node.start_mark.line + 1}: expected a mapping of fields at the top level")
    lines = _node_lines(node) if node is not None else {(): 1}
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:  # compose succeeded, so this is a constructor error (bad tag...)
        raise ConfigError(f"{source}: YAML cannot be loaded ({exc})") from None
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(validation_messages(exc, source=source, lines=lines)) from None


def read_config_text(path: str | os.PathLike, what: str) -> tuple[str, str]:
    """The text of a configuration file and its name for messages; ConfigError when it cannot be read."""
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8"), str(p)
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such {what} file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: cannot read {what} file ({exc})") from None


