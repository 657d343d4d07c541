"""Config files and command-line options name every localizer option the same way
(``camloc.options``, ``camloc.config``): the top-level ones by their flag, a group's in its table
by the flag without the group's prefix."""

from __future__ import annotations

import dataclasses

import pytest

from camloc.config import make_config, parse_config, run_config
from camloc.errors import ConfigError
from camloc.localizer_config import LocalizerConfig, option_methods, option_value
from camloc.options import RUN_OPTIONS, file_name

# A valid value other than the default for every option of camloc run.
CHANGED = {
    "filter": "se3", "association": "jcbb", "iterations": 2, "gate": 0.95, "null-cost": 12.0,
    "initial-sigma-xyz": 0.02, "initial-sigma-deg": 1.0, "beam-width": 8, "beam-delta": 10.0, "branch-delta": 6.0,
    "slip-inflation": 9.0, "slip-cost": 5.0, "cost": "mahalanobis", "margin": 2.0, "sequential": False,
    "jcbb-max-nodes": 100, "recheck": False, "recheck-margin": 1.0, "recheck-steal-margin": 4.0, "recheck-ray-margin": 5.0,
    "min-depth": 0.1,
    "max-depth": 5.0, "max-angle": 40.0, "max-distance": 6.0, "map": "prior", "map-sigma": 0.2,
}


def _file(flag: str, value, *, underscores: bool = False) -> dict:
    """The TOML document that sets option ``flag`` (as ``file_name`` writes it) and, for a
    method's option, selects that method."""
    path = RUN_OPTIONS[flag]
    table, _, key = file_name(path).rpartition(" ")
    if underscores:
        table, key = table.replace("-", "_"), key.replace("-", "_")
    document = {table.strip("[]"): {key: value}} if table else {key: value}
    methods = option_methods().get(path)
    if methods and flag != "association":
        document["association"] = methods[0]
    return document


def test_every_option_of_camloc_run_has_a_value_in_the_table():
    assert set(CHANGED) == set(RUN_OPTIONS)
    paths = []
    for field in dataclasses.fields(LocalizerConfig):
        group = getattr(LocalizerConfig(), field.name)
        paths += [f"{field.name}.{f.name}" for f in dataclasses.fields(group)] if dataclasses.is_dataclass(group) else [field.name]
    assert sorted(RUN_OPTIONS.values()) == sorted(paths)  # the one table covers every option, once


@pytest.mark.parametrize("flag", list(RUN_OPTIONS))
@pytest.mark.parametrize("underscores", [False, True], ids=["dashes", "underscores"])
def test_a_config_file_and_the_command_line_name_each_option_alike(flag, underscores):
    document = _file(flag, CHANGED[flag], underscores=underscores)
    from_file = make_config(parse_config(document, source="f.toml"))
    from_flags = run_config({flag: CHANGED[flag], "association": document.get("association")})
    assert from_file == from_flags
    assert option_value(from_file, RUN_OPTIONS[flag]) == CHANGED[flag] != option_value(LocalizerConfig(), RUN_OPTIONS[flag])


def test_the_names_of_the_issue():
    # issue 21: "gate = 0.95 is refused today"; issue 20's tables
    document = {"gate": 0.95, "iterations": 2, "initial-sigma-xyz": 0.02, "beam": {"width": 8},
                "recheck": {"steal-margin": 4.0}, "view": {"max-angle": 40.0}}
    config = make_config(parse_config(document, source="f.toml"))
    assert (config.gate, config.iterations, config.initial_sigma_xyz) == (0.95, 2, 0.02)
    assert (config.beam.width, config.recheck.steal_margin, config.view.max_angle_deg) == (8, 4.0, 40.0)
    assert config == run_config({"gate": 0.95, "iterations": 2, "initial-sigma-xyz": 0.02, "beam-width": 8,
                                 "recheck-steal-margin": 4.0, "max-angle": 40.0})


def test_precedence_is_defaults_then_the_file_then_the_command_line():
    config_file = parse_config({"iterations": 2, "gate": 0.95, "beam": {"width": 8, "delta": 9.0}}, source="f.toml")
    config = make_config(config_file, {"iterations": 5, "beam.width": 4, "gate": None})  # None: not given
    assert (config.iterations, config.beam.width) == (5, 4)                       # the command line
    assert (config.gate, config.beam.delta) == (0.95, 9.0)                        # the file
    assert config.beam.slip_cost == LocalizerConfig().beam.slip_cost             # the default


def test_a_recorded_configuration_is_a_config_file():
    """``summary.json``'s config (``asdict``: field names, every group) reads back as a config file,
    the groups of methods not selected included, since they hold their defaults."""
    config = run_config({"association": "best-friends", "margin": 2.0, "sequential": False, "max-angle": 40.0,
                         "recheck": False, "gate": 0.9})
    recorded = dataclasses.asdict(config)
    without_none = {k: ({kk: vv for kk, vv in v.items() if vv is not None} if isinstance(v, dict) else v)
                    for k, v in recorded.items() if v is not None}
    assert make_config(parse_config(without_none, source="summary")) == config


@pytest.mark.parametrize("document, message", [
    ({"view": {"max-angle": 30.0, "max_angle": 20.0}}, "f.toml: [view] max-angle and [view] max_angle are the same option"),
    ({"gate": "wide"}, "f.toml: gate must be a number, got 'wide'"),
    ({"recheck": {"enabled": 1}}, "f.toml: [recheck] enabled must be true or false, got 1"),
    ({"beam": {"width": 8.5}}, "f.toml: [beam] width must be an integer, got 8.5"),
    ({"best-friends": {"cost": "nll"}, "association": "beam", "jcbb": {"max-nodes": 5}},
     "f.toml: [jcbb] max-nodes applies only with association jcbb; the selected association is beam"),
    ({"association": "oracle", "best_friends": {"margin": 3.0}},
     "f.toml: [best-friends] margin applies only with association best-friends or jcbb; the selected association is oracle"),
    ({"margin": 2.0, "sequential": False, "max_depth": 3.0},
     "unknown option(s) margin (now [best-friends] margin), sequential (now [best-friends] sequential), "
     "max_depth (now [view] max-depth)"),
])
def test_config_file_errors_name_the_file_and_the_option(document, message):
    with pytest.raises(ConfigError) as error:
        make_config(parse_config(document, source="f.toml"))
    assert message in str(error.value)


def test_a_config_file_with_a_byte_order_mark_is_read(tmp_path):
    from camloc.config import read_config_file

    path = tmp_path / "options.toml"
    path.write_bytes("\ufeffgate = 0.95\n[beam]\nwidth = 8\n".encode("utf-8"))
    config = make_config(read_config_file(path))
    assert (config.gate, config.beam.width) == (0.95, 8)
    path.write_bytes(b"\xff\xfegate")  # UTF-16: not UTF-8, named as bad TOML rather than a traceback
    with pytest.raises(ConfigError, match="not valid TOML"):
        read_config_file(path)
