"""Shared pieces of the command line: consoles, the options every command words the same way, and
the one place where errors, bad options and Ctrl-C become a line on stderr and an exit status."""

from __future__ import annotations

import importlib
import io
import os
import re
import sys
from enum import Enum
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperCommand, TyperGroup, TyperOption

try:  # typer 0.2x carries its own copy of click
    from typer._click.exceptions import UsageError
except ImportError:  # older typer runs on click itself
    from click.exceptions import UsageError

from camloc.cli.interrupts import EXIT_INTERRUPTED, caused_by_interrupt, command_settled
from camloc.errors import CamlocError

console = Console()
err_console = Console(stderr=True)

EXIT_BAD_INPUT = 2
# stdout's reader left before the command printed everything: rich's status then, and ours
EXIT_STDOUT_CLOSED = 1

# The placeholders of the two kinds of input, the same in every command's usage line and help.
DATASET = "DATASET"
RUN_DIR = "RUN_DIR"


def print_error(message: str) -> None:
    """``error: <message>`` on stderr, one line however long (paths stay whole and copyable)."""
    err_console.print(f"[bold red]error:[/] {escape(message)}", markup=True, highlight=False, soft_wrap=True)


def print_warnings(warnings: Any, source: Any = None) -> None:
    """``warning: [<source>: ]<message>`` on stderr, one line each (a log or grep keeps it whole).

    Every command prints its warnings this way, under ``--quiet`` too: quiet silences progress and
    tables, not what a script run quietly must still be told (the estimate is odometry alone, the
    map looks incomplete). Under ``--json`` they are in the object instead (its ``warnings``), so
    the commands do not call this then.
    """
    where = f"{escape(str(source))}: " if source is not None else ""
    for warning in warnings:
        err_console.print(f"[yellow]warning:[/] {where}{escape(str(warning))}", highlight=False, soft_wrap=True)


class _FlagsWithoutValueType:
    """Flags listed in ``--help`` without a value type: typer shows ``<bool>``, a value the flag
    refuses (``--json true`` is an error)."""

    def get_params(self, ctx: typer.Context) -> list:
        params = super().get_params(ctx)  # type: ignore[misc]
        for param in params:
            if isinstance(param, TyperOption) and param.is_flag and param.metavar is None:
                param.metavar = ""
        return params


class CamlocCommand(_FlagsWithoutValueType, TyperCommand):
    """Every camloc command (``app.command(name, cls=CamlocCommand)``): its options' defaults are
    written into their help when ``--help`` is shown (``with_default``), and its usage line names
    arguments the usual way, ``NAME`` and ``[NAME]`` when optional."""

    def collect_usage_pieces(self, ctx: typer.Context) -> list[str]:
        # typer writes a required argument {NAME}, which reads as a set of choices
        return [piece[1:-1] if piece.startswith("{") and piece.endswith("}") else piece
                for piece in super().collect_usage_pieces(ctx)]

    def format_help(self, ctx: typer.Context, formatter: Any) -> Any:
        for param in self.get_params(ctx):
            if param.help and "{" in param.help:
                param.help = _resolve_defaults(param)
        return super().format_help(ctx, formatter)


class CamlocGroup(_FlagsWithoutValueType, TyperGroup):
    """The ``camloc`` group: every command runs through ``invoke``, which is where a
    ``CamlocError`` (bad input), a bad option and Ctrl-C end, the same way in every command."""

    def parse_args(self, ctx: typer.Context, args: list[str]) -> list[str]:
        given = bool(args)  # the parser consumes the list
        try:
            return super().parse_args(ctx, args)
        except UsageError as error:
            if not given:  # plain 'camloc': the help, as no_args_is_help says
                raise
            _usage_error(error, ctx)

    def invoke(self, ctx: typer.Context) -> Any:
        try:
            return self._invoke(ctx)
        finally:
            command_settled()

    def _invoke(self, ctx: typer.Context) -> Any:
        try:
            return super().invoke(ctx)
        except typer.Exit:
            raise  # a command's own exit status (sweep's 130 after its own message)
        except BaseException as error:
            # Ctrl-C first, whatever it became on its way out: inside a numba kernel it surfaces
            # as a SystemError whose cause is the KeyboardInterrupt
            if caused_by_interrupt(error):
                say_interrupted()
                raise typer.Exit(EXIT_INTERRUPTED) from None
            if isinstance(error, CamlocError):
                print_error(str(error))
                raise typer.Exit(EXIT_BAD_INPUT) from None
            if isinstance(error, BrokenPipeError) and error.filename is None:
                # stdout's reader left ('camloc info --json | head -c 1'): end as rich's tables
                # end then, silently with status 1; the outputs were written before the printing
                _discard_stdout()
                raise typer.Exit(EXIT_STDOUT_CLOSED) from None
            if isinstance(error, OSError):
                # the machine refused (a folder not writable, a file where a folder goes, a full
                # disk): the file and the reason, as for bad input; outputs stay whole or absent
                print_error(describe_os_error(error))
                raise typer.Exit(EXIT_BAD_INPUT) from None
            if isinstance(error, MemoryError):
                print_error("not enough memory for this command and its options (a very large count or size?)")
                raise typer.Exit(EXIT_BAD_INPUT) from None
            if isinstance(error, UsageError):
                _usage_error(error, ctx)
            raise


def _discard_stdout() -> None:
    """Point stdout at the null device, so that the interpreter's last flush of what is still
    buffered for a reader that has left does not report another broken pipe."""
    try:
        descriptor = sys.stdout.fileno()
    except (AttributeError, ValueError, io.UnsupportedOperation):  # not a file (a test's capture)
        return
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, descriptor)
    os.close(null)


def say_interrupted() -> None:
    """The one line of an interrupted command. Outputs are written whole or not at all, so it
    leaves nothing half-written; say so rather than print a traceback or nothing."""
    err_console.print("interrupted", style="yellow", highlight=False)


def describe_os_error(error: OSError) -> str:
    """``<file>: <reason>`` of an error of the file system (both files of a rename)."""
    reason = error.strerror or str(error)
    files = [str(name) for name in (error.filename, error.filename2) if name is not None]
    if len(files) == 2:
        return f"cannot move {files[0]} to {files[1]}: {reason}"
    return f"{files[0]}: {reason}" if files else reason


def _usage_error(error: UsageError, ctx: typer.Context) -> None:
    """A bad option or argument: one line and where to look, instead of click's usage block and
    framed panel; exit status 2."""
    where = error.ctx.command_path if error.ctx is not None else ctx.command_path
    if error.ctx is None and ctx.invoked_subcommand:  # an option's missing value: its command's help
        where = f"{ctx.command_path} {ctx.invoked_subcommand}"
    print_error(f"{plain_usage_message(error.format_message())} (see '{where} --help')")
    raise typer.Exit(EXIT_BAD_INPUT) from None


# How typer (through pydantic) words a value that is none of an option's choices.
_NOT_A_CHOICE = re.compile(r"Value error, (?P<value>.+) is not one of (?P<choices>.+?)\.?$")


def plain_usage_message(message: str) -> str:
    """A bad option's message in camloc's words: ``expected one of none, se3, sim3, found 'foo'``
    rather than pydantic's ``Value error, 'foo' is not one of 'none', 'se3', 'sim3'.``, the same for
    every option with choices."""
    match = _NOT_A_CHOICE.search(message)
    if match is not None:
        choices = ", ".join(choice.strip().strip("'") for choice in match["choices"].split(","))
        message = f"{message[:match.start()]}expected one of {choices}, found {match['value']}"
    return message.replace("Value error, ", "")


# The library's option classes whose defaults the help shows ("{localizer.iterations}"); they are
# imported only when --help is printed, so that starting a command does not pay for scipy.
_DEFAULT_SOURCES = {
    "localizer": ("camloc.localizer", "LocalizerConfig"),
    "simulation": ("camloc.simulate", "SimulationConfig"),
    "planar_simulation": ("camloc.simulate_planar", "PlanarSimulationConfig"),
    "smoother": ("camloc.smoother", "SmootherConfig"),
}
_PLACEHOLDER = re.compile(r"\{(?:default|(\w+)\.([\w.]+))\}")


def with_default(text: str, source: str = "default") -> str:
    """``text`` followed by ``Default: <value>.``, the one way every option states its default.

    The value is not typed again: ``source`` ``"default"`` is the option's own default, and
    ``"<kind>.<field>"`` (kinds of ``_DEFAULT_SOURCES``; ``<field>`` may be dotted,
    ``"localizer.beam.width"``) the default of a library option that
    the command leaves to the library; both are filled in when ``--help`` is shown.
    """
    return f"{text} Default: {{{source}}}."


def _resolve_defaults(param: Any) -> str:
    def value(match: re.Match) -> str:
        if match[1] is None:
            default = param.default
        else:
            module, name = _DEFAULT_SOURCES[match[1]]
            default = getattr(importlib.import_module(module), name)()
            for field in match[2].split("."):  # a group's option: "localizer.beam.width"
                default = getattr(default, field)
        return _describe_default(param, default)

    return _PLACEHOLDER.sub(value, param.help)


def _describe_default(param: Any, value: Any) -> str:
    """A default as the help shows it: enums by value, floats shortest, flags on/off or by name."""
    if isinstance(value, bool):
        if param.secondary_opts:
            return param.opts[0] if value else param.secondary_opts[0]
        return "on" if value else "off"
    if isinstance(value, Enum):
        return str(value.value)
    if isinstance(value, float):
        text = repr(value)  # 2.0, 0.99, inf; a long one shortened: 0.0316228
        return text if len(text) <= 8 else f"{value:.6g}"
    return str(value)


def library_option(text: str, source: str, *names: str, **limits: Any) -> Any:
    """An option that, when not given (None), leaves the value to the library: to its default,
    named by ``source`` as in ``with_default``, or to a file of options (``run --config``)."""
    return typer.Option(None, *names, help=with_default(text, source), show_default=False, **limits)


def quiet_option() -> Any:
    return typer.Option(False, "--quiet", "-q", help=with_default(
        "Print no progress and no tables: only warnings and errors, on stderr."), show_default=False)


def json_option(what: str, *, instead: str = "tables") -> Any:
    return typer.Option(False, "--json", help=with_default(
        f"Print {what} as one JSON object (keys listed in docs/json.md) instead of {instead}."),
        show_default=False)


def force_option(what: str) -> Any:
    return typer.Option(False, "--force", help=with_default(
        f"Replace {what} when it already exists (without it, an existing one is refused)."),
        show_default=False)


def run_dir_argument(text: str = "Run folder written by 'camloc run'.", *, required: bool = True) -> Any:
    return typer.Argument(... if required else None, metavar=RUN_DIR, help=text, show_default=False)


def dataset_argument(text: str, *, required: bool = True) -> Any:
    return typer.Argument(... if required else None, metavar=DATASET, help=text, show_default=False)


def read_true_map(path: Any, run: Any) -> Any:
    """The g2o file ``path`` given as ``--true-map`` of the run ``run`` (a ``RunResult``): read
    without its warnings (its map alone is used), and refused unless it is the run's world (its
    poses, odometry and observations), whose map may differ from the run's: the true map of
    another world was scored and drawn without a word, its ids meaning other landmarks."""
    import warnings

    from camloc.g2o import G2oWarning, read_g2o
    from camloc.smoother import check_run_matches

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", G2oWarning)
        truth = read_g2o(path)
    check_run_matches(truth, run, with_map=False, hint="expected the true map of the world the run was made from "
                      "('camloc simulate' writes it beside the world, <stem>.true-map.g2o)")
    return truth


def echo_json(obj: Any, *, enabled: bool) -> bool:
    """Print ``obj`` as strict JSON on stdout when ``enabled`` (``--json``); True when printed."""
    if enabled:
        from camloc.results import dumps_json

        typer.echo(dumps_json(obj), nl=False)
    return enabled
