"""Reading configuration documents (TOML) into validated pydantic models.

Plans, rig configurations and scenes are all TOML files validated by pydantic; a user who
gets one wrong must be told which file and which field, and what was expected, never see
a pydantic traceback.  This module is the one place that turns those failures into
:class:`~gonio.errors.ConfigError` messages.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from gonio.errors import ConfigError

M = TypeVar("M", bound=BaseModel)


def validation_message(err: ValidationError, source: str) -> str:
    """One line per invalid field: ``SOURCE: field 'a.b': what is wrong (got VALUE)``.

    Location parts that pydantic adds for union members and generic containers
    (``list[...]``, ``function-after[...]``) are dropped, so the name is the one in the file.
    """
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"] if "[" not in str(p)) or "(top level)"
        got = f" (got {e['input']!r})" if "input" in e and not isinstance(e["input"], dict) else ""
        lines.append(f"{source}: field '{loc}': {e['msg']}{got}")
    return "\n".join(lines)


def validate(model: type[M], data: Any, source: str) -> M:
    """Validate ``data`` as ``model``.

    Raises
    ------
    ConfigError
        Naming ``source`` and every offending field.
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(validation_message(exc, source)) from None


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """Parse a TOML file describing ``what`` (e.g. ``"plan"``).

    Raises
    ------
    ConfigError
        When the file cannot be read or is not valid TOML (names the file).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: cannot read {what}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        why = getattr(exc, "strerror", None) or exc
        raise ConfigError(f"{p}: cannot read {what}: {why}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: {what} is not a valid TOML file: {exc}") from None
