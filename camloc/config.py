"""Localizer options from a TOML file and from command-line overrides, merged in one place.

Precedence: ``LocalizerConfig`` defaults < the TOML file < options given on the command line.
A TOML file holds the option names of ``LocalizerConfig`` at top level or in a ``[localizer]`` table:

    association = "best-friends"
    iterations = 3
    gate_probability = 0.99
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any, Mapping, Optional

from camloc.errors import ConfigError
from camloc.localizer import LocalizerConfig

FIELD_NAMES = tuple(f.name for f in dataclasses.fields(LocalizerConfig))


def read_config_file(path: str | Path) -> dict[str, Any]:
    """Option values of a TOML file; ConfigError for a missing file, bad TOML or unknown keys."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            document = tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, expected a TOML file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: not valid TOML ({error})") from None
    values = document.get("localizer", document)
    if not isinstance(values, dict):
        raise ConfigError(f"{path}: localizer must be a table of options ([localizer]), found {type(values).__name__} {values!r}")
    elsewhere = sorted(set(document) - {"localizer"}) if values is not document else []
    if elsewhere:
        raise ConfigError(f"{path}: options both at top level ({', '.join(elsewhere)}) and in [localizer]; "
                          "expected them in one place")
    unknown = sorted(set(values) - set(FIELD_NAMES))
    if unknown:
        raise ConfigError(f"{path}: unknown option(s) {', '.join(unknown)}; expected some of {', '.join(FIELD_NAMES)}")
    for name, value in values.items():
        reason = _type_error(name, value)
        if reason is not None:
            raise ConfigError(f"{path}: {reason}")
    return dict(values)


def make_config(
    file_values: Optional[Mapping[str, Any]] = None, overrides: Optional[Mapping[str, Any]] = None
) -> LocalizerConfig:
    """Defaults, then file values, then the overrides that are not None; validated."""
    values: dict[str, Any] = {}
    values.update(file_values or {})
    values.update({k: v for k, v in (overrides or {}).items() if v is not None})
    try:
        config = LocalizerConfig(**values)
    except TypeError as error:
        raise ConfigError(str(error)) from None
    _check_types(config)
    config.validate()
    return config


def _check_types(config: LocalizerConfig) -> None:
    for name in FIELD_NAMES:
        reason = _type_error(name, getattr(config, name))
        if reason is not None:
            raise ConfigError(reason)


def _type_error(name: str, value: Any) -> Optional[str]:
    """Why ``value`` cannot be option ``name`` (its default's type; a number where the default is a
    float or None), or None when it can."""
    default = getattr(_DEFAULTS, name)
    expected = type(default) if default is not None else (int, float)
    if isinstance(default, float):
        expected = (int, float)
    if value is not None and (not isinstance(value, expected) or (isinstance(value, bool) and not isinstance(default, bool))):
        return f"option {name} must be of type {getattr(expected, '__name__', 'number')}, got {value!r}"
    return None


_DEFAULTS = LocalizerConfig()
