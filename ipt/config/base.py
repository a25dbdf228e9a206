"""What every settings model shares: the strict base model, the one configuration error, and the YAML loaders.

Every model forbids unknown keys (:class:`StrictModel`), so a typo in a YAML file is reported instead of
silently ignored; :func:`load_yaml_model` turns any problem with a file into one :class:`ConfigError` line
that names the file and the keys.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from ipt.errors import IptError
from ipt.fileio import read_text_file


class ConfigError(IptError):
    """A configuration file is missing, unreadable or invalid."""


class StrictModel(BaseModel):
    """Base for every settings model: unknown keys are errors, instances are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def finite_float(value: object) -> float | None:
    """``value`` as a float if it is a real number that fits one (not bool, not inf/nan), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # an integer too large for a float
        return None
    return number if math.isfinite(number) else None


M = TypeVar("M", bound=BaseModel)


_MAX_PROBLEMS = 12
"""Problems named in one configuration error; the rest are counted ("... and N more")."""
_MAX_PART_CHARS = 200
"""Longest description of one problem (a key or a value can be megabytes long in a broken file)."""


def _shorten(text: str, limit: int = _MAX_PART_CHARS) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _describe_validation_error(exc: ValidationError) -> str:
    parts = []
    errors = exc.errors()
    for err in errors[:_MAX_PROBLEMS]:
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        if not where.isprintable():
            where = repr(where)
        msg = err["msg"]
        value = err.get("input")
        if isinstance(value, float) and math.isnan(value):
            msg = "nan is not a number"  # a bound check's "should be less than or equal to 1000" misled
        elif err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "missing":
            msg = "missing key"
        parts.append(_shorten(f"{where}: {msg}"))
    if len(errors) > _MAX_PROBLEMS:
        parts.append(f"... and {len(errors) - _MAX_PROBLEMS} more")
    return "; ".join(parts)


def read_yaml_mapping(path: Path, error: type[IptError] = ConfigError) -> dict[str, Any]:
    """Read a YAML file whose top level is a mapping; raise ``error`` naming the file otherwise."""
    text = read_text_file(path, error, "a YAML file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{path}: not valid YAML{where}") from None
    except RecursionError:
        raise error(f"{path}: not usable YAML: nested too deeply") from None
    except Exception as exc:
        # PyYAML's own constructors raise plain exceptions for some scalars they claim to resolve:
        # ValueError for a date like 2001-13-45 or an integer of more than 4300 digits, KeyError for
        # `!!bool maybe`, AttributeError for `!!timestamp x`, IndexError for an empty `!!int`.
        what = _shorten(str(exc) or type(exc).__name__)
        raise error(f"{path}: not usable YAML: a value cannot be read ({what})") from None
    if data is None:
        raise error(f"{path}: the file is empty")
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    """Load ``path`` as YAML and validate it as ``model``; any problem is one :class:`ConfigError`."""
    p = Path(path)
    data = read_yaml_mapping(p)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{p}: {_describe_validation_error(exc)}") from None


def shipped_config_path(name: str) -> Path:
    """Path of an example config shipped inside the package (e.g. ``arena.yaml``)."""
    return Path(str(resources.files("ipt.config") / name))
