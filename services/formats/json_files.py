"""Reading, validating and writing the project's JSON files, with errors that name the file and field."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, TypeAdapter, ValidationError

from services.errors import InputError
from services.formats.files import write_text_atomically

Model = TypeVar("Model")


def _field_path(location: tuple, tags: frozenset[str]) -> str:
    """pydantic's error location as ``devices.camera.R`` or ``frames[3].bit``, without union tags."""
    path = ""
    for previous, part in zip((None,) + location[:-1], location):
        if isinstance(part, int):
            path += f"[{part}]"
        elif isinstance(previous, int) and part in tags:
            continue  # the discriminator tag pydantic inserts after a list index
        else:
            path += f".{part}" if path else str(part)
    return path


def describe_validation_error(source: str, error: ValidationError, tags: frozenset[str] = frozenset()) -> str:
    """One line per problem: ``source: field: message``."""
    lines = []
    for item in error.errors():
        message = item["msg"].removeprefix("Value error, ")
        field = _field_path(tuple(item["loc"]), tags)
        lines.append(f"{source}: {field}: {message}" if field else f"{source}: {message}")
    return "\n".join(lines)


def validate_json(schema: type[Model] | TypeAdapter, text: str, source: str,
                  tags: frozenset[str] = frozenset()) -> Model:
    """Validate JSON text against a pydantic model or type adapter; an ``InputError`` names ``source``."""
    try:
        if isinstance(schema, TypeAdapter):
            return schema.validate_json(text)
        return schema.model_validate_json(text)
    except ValidationError as error:
        raise InputError(describe_validation_error(source, error, tags)) from None


def read_text(path: str | Path, what: str) -> str:
    """The text of a file, or an ``InputError`` that says which ``what`` could not be read and why."""
    path = Path(path)
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        reason = getattr(error, "strerror", None) or error
        raise InputError(f"{path}: cannot read the {what} ({reason})") from None


def write_model(model: BaseModel, path: str | Path) -> Path:
    """A pydantic model as indented JSON, atomically."""
    return write_text_atomically(path, model.model_dump_json(indent=2) + "\n")
