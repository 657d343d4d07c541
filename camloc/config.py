"""Localizer options from a TOML file and from command-line overrides, merged in one place.

Precedence: ``LocalizerConfig`` defaults < the TOML file < options given on the command line.
A TOML file names the options as the command line does (``camloc.options``): the top-level ones
by their flag, a group's in its table by the flag without the group's prefix, with dashes or
underscores; all at top level, or all under a ``[localizer]`` table:

    association = "beam"
    iterations = 3
    gate = 0.99

    [beam]
    width = 8            # --beam-width 8

    [recheck]
    steal-margin = 6.0   # --recheck-steal-margin 6

A key may also be the field's name in ``LocalizerConfig`` (``max_angle_deg``), so the
``config`` that ``summary.json`` records, written as TOML, is a config file.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any, Mapping, Optional

from camloc.errors import ConfigError
from camloc.localizer_config import LocalizerConfig, OptionError, option_value
from camloc.options import FLAG_OF_PATH, NEGATED_FLAGS, RUN_OPTIONS, accepted_keys, file_name, key_of, localizer_overrides, table_of

# table ("" for top level; "best-friends" and "best_friends" alike) -> key -> option path
_KEYS: dict[str, dict[str, str]] = {}
for _path in RUN_OPTIONS.values():
    for _table in dict.fromkeys((table_of(_path), table_of(_path).replace("-", "_"))):
        _KEYS.setdefault(_table, {}).update(dict.fromkeys(accepted_keys(_path), _path))

# The flat field names of camloc 0.1 that are not a flag's name with underscores -> that flag.
_FORMER_NAMES = {"gate_probability": "gate", "max_angle_deg": "max-angle"}


@dataclasses.dataclass(frozen=True)
class ConfigFile:
    """The options of a config file: ``values`` by option path (``"beam.width"``), and where they
    were read, to name an option as the file writes it."""

    source: str
    values: dict[str, Any]
    table: str = ""  # "localizer" when the options sit in a [localizer] table

    def name(self, path: str) -> str:
        """``<source>: [beam] width``: option ``path`` as this file writes it."""
        table = ".".join(filter(None, (self.table, table_of(path))))
        return f"{self.source}: " + (f"[{table}] " if table else "") + key_of(path)


def read_toml(path: str | Path, *, what: str = "config file") -> dict[str, Any]:
    """The document of a TOML file; ConfigError naming it (and ``what`` it should be) for a missing
    file, a folder or bad TOML."""
    path = Path(path)
    if path.is_char_device() or path.is_block_device():  # /dev/zero would be read forever
        raise ConfigError(f"{path}: is a device, expected a TOML {what}")
    try:
        # a byte order mark, as some Windows editors write, is not TOML but says nothing either
        return tomllib.loads(path.read_bytes().decode("utf-8").removeprefix("\ufeff"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a directory, expected a TOML {what}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise ConfigError(f"{path}: not valid TOML ({error})") from None


def read_config_file(path: str | Path) -> ConfigFile:
    """The options of a TOML file; ConfigError for a missing file, bad TOML or unknown keys."""
    return parse_config(read_toml(path), source=str(path))


def parse_config(document: Mapping[str, Any], *, source: str) -> ConfigFile:
    """The options of a parsed TOML document (``source`` names it in errors)."""
    table = "localizer" if "localizer" in document else ""
    values = document.get("localizer", document)
    if not isinstance(values, dict):
        raise ConfigError(f"{source}: localizer must be a table of options ([localizer]), found {type(values).__name__} {values!r}")
    elsewhere = sorted(set(document) - {"localizer"}) if table else []
    if elsewhere:
        raise ConfigError(f"{source}: options both at top level ({', '.join(elsewhere)}) and in [localizer]; "
                          "expected them in one place")
    found: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    unknown: list[str] = []
    for key, value in values.items():
        if key in _KEYS and key != "" and isinstance(value, dict):
            entries = [(f"[{key}] {name}", _KEYS[key].get(name), item) for name, item in value.items()]
        else:
            entries = [(key, _KEYS[""].get(key), value)]
        for written, path, item in entries:
            if path is None:
                unknown.append(written + _former_name(written))
            elif path in found:
                raise ConfigError(f"{source}: {spelled[path]} and {written} are the same option; expected it once")
            else:
                found[path], spelled[path] = item, written
    if unknown:
        raise ConfigError(f"{source}: unknown option(s) {', '.join(unknown)}; expected some of {_valid_names()}")
    config_file = ConfigFile(source, found, table)
    for path, value in found.items():
        _check_type(path, value, config_file.name(path))
    return config_file


def make_config(config_file: Optional[ConfigFile] = None, overrides: Optional[Mapping[str, Any]] = None) -> LocalizerConfig:
    """Defaults, then the file's values, then the ``overrides`` (option path -> value, as given on
    the command line) that are not None; validated. An error names the option as its user wrote
    it: ``--beam-width`` or ``<file>: [beam] width``."""
    given: dict[str, tuple[Any, str]] = {}
    if config_file is not None:
        given.update({path: (value, config_file.name(path)) for path, value in config_file.values.items()})
    for path, value in (overrides or {}).items():
        if value is not None:
            given[path] = (value, _flag(path, value))
            _check_type(path, value, given[path][1])
    config = with_options(LocalizerConfig(), {path: value for path, (value, _) in given.items()})
    try:
        config.validate()
    except OptionError as error:
        raise ConfigError(f"{given[error.path][1] if error.path in given else error.path} {error.reason}") from None
    return config


def run_config(options: Mapping[str, Any], config_file: Optional[ConfigFile] = None) -> LocalizerConfig:
    """The validated ``LocalizerConfig`` of run options by command-line name (``camloc.options``'
    names), over ``config_file`` (or None). Raises ConfigError for a bad name or value."""
    return make_config(config_file, localizer_overrides(options))


def with_options(config: LocalizerConfig, values: Mapping[str, Any]) -> LocalizerConfig:
    """``config`` with the options of ``values`` (option path -> value) replaced; not validated."""
    top: dict[str, Any] = {}
    groups: dict[str, dict[str, Any]] = {}
    for path, value in values.items():
        group, _, name = path.rpartition(".")
        (groups.setdefault(group, {}) if group else top)[name] = value
    return dataclasses.replace(config, **top, **{g: dataclasses.replace(getattr(config, g), **v) for g, v in groups.items()})


def _check_type(path: str, value: Any, name: str) -> None:
    """ConfigError unless ``value`` is of option ``path``'s kind: its default's type, a number
    where the default is a float or None (the data's own value)."""
    default = option_value(_DEFAULTS, path)
    if isinstance(default, bool):
        ok, kind = isinstance(value, bool), "true or false"
    elif isinstance(default, int):
        ok, kind = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(default, str):
        ok, kind = isinstance(value, str), "a string"
    else:
        ok, kind = isinstance(value, (int, float)) and not isinstance(value, bool), "a number"
    if not ok:
        raise ConfigError(f"{name} must be {kind}, got {value!r}")


def _flag(path: str, value: Any) -> str:
    """Option ``path`` as the command line gives ``value``: ``--beam-width``, ``--batch``."""
    flag = FLAG_OF_PATH[path]
    negated = {name: negation for negation, name in NEGATED_FLAGS.items()}
    return f"--{negated[flag]}" if value is False and flag in negated else f"--{flag}"


def _former_name(written: str) -> str:
    """`` (now [beam] width)`` for a flat option name of camloc 0.1 (``beam_width``), else ``""``."""
    flag = _FORMER_NAMES.get(written, written.replace("_", "-"))
    moved = flag in RUN_OPTIONS and (table_of(RUN_OPTIONS[flag]) or written in _FORMER_NAMES)
    return f" (now {file_name(RUN_OPTIONS[flag])})" if moved else ""


def _valid_names() -> str:
    tables: dict[str, list[str]] = {}
    for path in RUN_OPTIONS.values():
        tables.setdefault(table_of(path), []).append(key_of(path))
    return "; ".join((f"[{table}] " if table else "") + ", ".join(keys) for table, keys in tables.items())


_DEFAULTS = LocalizerConfig()
