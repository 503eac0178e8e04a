"""The ``torchiid`` command line: a thin layer over the library.

Every command is a module of :mod:`torchiid.commands` named in :data:`COMMANDS`, with
``add_arguments(parser)`` (the options; it imports nothing heavy) and ``run(args)`` (the
work; it imports torch and the rest when it runs), so ``torchiid --help``, ``--version`` and
``torchiid COMMAND --help`` start at once. The commands that run long share one set of run
options: ``--no-progress``, ``--device``, ``--threads N``, ``-q/--quiet`` and
``-v/--verbose`` (``-q`` and ``-v`` also before the command: ``torchiid -v decompose ...``).

Exit status, the same for every command:

* 0: everything was done (for ``decompose``: written now, or by an earlier run).
* 1: something failed: some inputs (each reported in its line; the others were done), or an
  internal error (reported in one line; ``-v`` adds its traceback).
* 2: usage or set-up error, found before any work: options, parameters, missing or
  unreadable files, an output folder that cannot be written.
* 130: interrupted (Ctrl-C, SIGINT or SIGTERM); what was finished before stays complete.

Errors a user can cause end in one line, ``torchiid: error: ...``, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NoReturn

from torchiid._version import __version__
from torchiid.commands.common import run_environment, run_options, verbosity_options

if TYPE_CHECKING:
    from torchiid.params import Parameters
    from torchiid.pipeline.compile_ahead import CompileAhead

__all__ = ["COMMANDS", "Command", "build_parser", "console_main", "main"]

log = logging.getLogger("torchiid")

EXIT_STATUS = """\
exit status: 0 done; 1 failed (some inputs, each reported in one line, or an internal error);
2 usage or set-up error (nothing was processed); 130 interrupted (Ctrl-C, SIGTERM)."""


@dataclass(frozen=True)
class Command:
    """One ``torchiid`` command.

    Attributes:
        name: the word on the command line.
        module: its module in :mod:`torchiid.commands`, with ``add_arguments(parser)`` and
            ``run(args) -> int`` (and optionally ``DESCRIPTION`` and ``EPILOG`` strings).
        help: the one line ``torchiid --help`` shows.
        runs_long: takes the run options (``--no-progress``, ``--device``, ``--threads``,
            ``--memory-limit``).
    """

    name: str
    module: str
    help: str
    runs_long: bool = True


#: the commands, in the order ``torchiid --help`` lists them
COMMANDS: tuple[Command, ...] = (
    Command("decompose", "decompose", "split photos into reflectance and shading"),
    Command("decompose-video", "video", "decompose a video, its frames tied together"),
    Command("edit", "edit", "edit a photo through its reflectance and shading"),
    Command("eval", "eval", "score a method or saved results on a benchmark"),
    Command("features", "features", "pictures of a photo's Stage 0 features"),
    Command("export-onnx", "export_onnx", "export the feature extractor to ONNX", runs_long=False),
    Command("app", "app", "decompose and edit photos in the browser"),
)


class _Parser(argparse.ArgumentParser):
    """A parser whose usage errors are one line, as every other error of the command line.

    The usage summary of a command runs to a dozen lines; the error names the option, and
    ``--help`` is one command away.
    """

    def error(self, message: str) -> NoReturn:
        """Print ``torchiid: error: MESSAGE (see 'PROG --help')`` and exit with status 2."""
        self.exit(2, f"torchiid: error: {message} (see '{self.prog} --help')\n")

    def parse_args(self, args=None, namespace=None):  # type: ignore[no-untyped-def, override]
        """As argparse's, with arguments no option takes named against the command's help."""
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            command = getattr(parsed, "command", None)
            prog = f"{self.prog} {command}" if command else self.prog
            self.exit(
                2,
                f"torchiid: error: unrecognized arguments: {' '.join(extras)} "
                f"(see '{prog} --help')\n",
            )
        return parsed


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions and epilogs as written; option help in a column wide enough for the options."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=30)


def _command_list() -> str:
    """Every command with its one line (``torchiid --help``)."""
    width = max(len(c.name) for c in COMMANDS) + 2
    return "commands:\n" + "\n".join(f"  {c.name:<{width}}{c.help}" for c in COMMANDS)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``torchiid`` command."""
    parser = _Parser(
        prog="torchiid",
        usage="%(prog)s [-h] [--version] [-q | -v] COMMAND ...",
        description="Intrinsic image decomposition (I = R x S) with semantic hierarchical priors."
        f"\n\n{_command_list()}\n\n'torchiid COMMAND --help' describes each command.",
        epilog=EXIT_STATUS,
        formatter_class=_Formatter,
    )
    parser.add_argument("--version", action="version", version=f"torchiid {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", action="store_true", help="print only errors")
    verbosity.add_argument("-v", "--verbose", action="store_true", help="print details")
    sub = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", help=argparse.SUPPRESS, prog="torchiid"
    )
    run_parent, verbosity_parent = run_options(), verbosity_options()
    for command in COMMANDS:
        module = _module(command.name)  # light: the options only
        epilog = getattr(module, "EPILOG", None)
        p = sub.add_parser(
            command.name,
            help=command.help,
            description=getattr(module, "DESCRIPTION", command.help),
            epilog=f"{epilog}\n\n{EXIT_STATUS}" if epilog else EXIT_STATUS,
            parents=[run_parent if command.runs_long else verbosity_parent],
            formatter_class=_Formatter,
        )
        module.add_arguments(p)
    return parser


def main(argv: Sequence[str] | None = None, *, own_process: bool = False) -> int:
    """Entry point of the ``torchiid`` console script; returns the exit status.

    ``own_process``: the process is the command's alone (the console script), so its
    allocator is set for the run (:func:`~torchiid.core.memory.share_one_malloc_arena`);
    called from Python, the caller's process keeps its own.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.quiet and args.verbose:
        parser.error("-q/--quiet and -v/--verbose exclude each other")
    if args.quiet:
        args.no_progress = True
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.ERROR if args.quiet else logging.WARNING,
        format="torchiid: %(message)s",
    )
    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:
        # SIGTERM (kill, timeout, a closed session) cleans up like Ctrl-C
        previous = signal.signal(signal.SIGTERM, _interrupt)
    threads = getattr(args, "threads", None)
    # before torch loads (its OpenMP pool size); workers inherit both
    environment = run_environment(threads, getattr(args, "memory_limit", None))
    torch_threads = None
    from torchiid.core.exceptions import InputWarning

    notes = warnings.catch_warnings()  # the run's warning settings, given back after it
    notes.__enter__()
    # what the loader changed in an input is a note, even where warnings are made errors
    warnings.filterwarnings("always", category=InputWarning)
    warnings.showwarning = _notes(warnings.showwarning, args.quiet)
    try:
        from torchiid.core.memory import memory_limit, share_one_malloc_arena

        memory_limit()  # a bad TORCHIID_MEMORY_LIMIT stops the run here, not once per image
        if own_process:
            share_one_malloc_arena()
        if threads is not None:
            import torch

            torch_threads = torch.get_num_threads()
            torch.set_num_threads(threads)
        from torchiid.core.first_compile import notify_first_compile
        from torchiid.pipeline.compile_ahead import compiling_ahead

        with compiling_ahead(lambda: _run_params(args)) as ahead:
            with notify_first_compile(lambda: _first_compilation(args, ahead)):
                return _module(args.command).run(args)
    except KeyboardInterrupt:
        print("torchiid: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - one line; the traceback with -v
        return _report(exc)
    finally:
        if torch_threads is not None:  # main() called from Python keeps its own settings
            import torch

            torch.set_num_threads(torch_threads)
        _restore(environment)
        notes.__exit__(None, None, None)
        if main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def console_main() -> NoReturn:
    """The ``torchiid`` console script: :func:`main`, then the process ends at once.

    A process that has loaded torch spends a few tenths of a second at exit tearing down
    thousands of modules, longer than ``torchiid --help`` takes in all. By the time
    :func:`main` returns, every output is written, closed and put in place, so the script
    flushes the standard streams and the log and leaves with :func:`os._exit`, skipping that
    teardown. A run that still has child processes (a pool that has not been joined) takes
    the interpreter's ordinary exit, which waits for them.
    """
    status = main(own_process=True)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``): nothing left to deliver
            pass
    logging.shutdown()
    children = sys.modules.get("multiprocessing")
    if children is not None and children.active_children():
        sys.exit(status)
    os._exit(status)


def _notes(shown: Callable[..., None], quiet: bool) -> Callable[..., None]:
    """``warnings.showwarning`` for a run: an input the loader changed is a one-line note."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ANN001
        from torchiid.core.exceptions import InputWarning

        if not issubclass(category, InputWarning):
            shown(message, category, filename, lineno, file, line)
        elif not quiet:
            print(f"torchiid: note: {message}", file=sys.stderr)

    return show


def _first_compilation(args: argparse.Namespace, ahead: CompileAhead) -> None:
    """The kernels compile (the first run in an environment): a note says so, above any bar.

    A command that runs Stage 2 on the CPU also has Stage 2's kernels compiled in a second
    process meanwhile (:mod:`torchiid.pipeline.compile_ahead`); a run on a GPU solves there,
    and a command without parameters (``features``) has no Stage 2.
    """
    if getattr(args, "preset", None) is not None and _on_cpu(args):
        ahead.start()
    if args.quiet:
        return
    from tqdm import tqdm

    from torchiid.core.first_compile import COMPILING

    tqdm.write(f"torchiid: note: {COMPILING}", file=sys.stderr)


def _on_cpu(args: argparse.Namespace) -> bool:
    """Whether the run solves on the CPU (its ``--device``, as the command resolves it)."""
    from torchiid.core.device import resolve_device

    try:
        return resolve_device(getattr(args, "device", None) or "cpu").type == "cpu"
    except Exception:  # noqa: BLE001 - a device that cannot be had: the command says so
        return False


def _run_params(args: argparse.Namespace) -> Parameters | None:
    """The run's parameters where the command takes them (``None``: it takes none).

    A command with ``--preset`` alone (``app``: the page's first preset) gives that preset.
    """
    if getattr(args, "preset", None) is None:
        return None
    from torchiid.commands.common import params_from_args
    from torchiid.params import Parameters

    try:
        if hasattr(args, "params"):
            return params_from_args(args)
        return Parameters.preset(args.preset)
    except Exception:  # noqa: BLE001 - the command itself reports bad parameters
        return None


def _module(name: str):
    """The module of command ``name``."""
    command = next(c for c in COMMANDS if c.name == name)
    return importlib.import_module(f"torchiid.commands.{command.module}")


def _report(exc: Exception) -> int:
    """Print an exception that ended a command in one line; returns the exit status."""
    from torchiid.core.exceptions import (
        TorchiidError,
        caused_by_interrupt,
        one_line,
        unimportable_dependency,
    )

    if isinstance(exc, TorchiidError):
        print(f"torchiid: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    broken = unimportable_dependency(exc)
    if broken is not None:  # the installation's fault: a set-up error
        print(f"torchiid: error: {broken}", file=sys.stderr)
        log.info("the error above came from here:", exc_info=exc)
        return 2
    if caused_by_interrupt(exc):  # Ctrl-C inside a compiled kernel
        print("torchiid: interrupted", file=sys.stderr)
        return 130
    print(
        f"torchiid: error: internal error ({type(exc).__name__}: {one_line(str(exc))}); "
        "rerun with --verbose for the traceback",
        file=sys.stderr,
    )
    log.info("the error above came from here:", exc_info=exc)
    return 1


def _restore(environment: dict[str, str | None]) -> None:
    for name, value in environment.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":  # pragma: no cover
    console_main()
