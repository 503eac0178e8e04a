"""Running the ``torchiid`` command end to end for the reliability tests.

:func:`run_cli` starts ``python -m torchiid.cli`` in a new process, like a user's shell.
:func:`run_many` runs many command lines that each end before any decomposition (usage and
set-up errors) in one process: it imports torchiid once, then forks a child per command line
that calls the console script's entry point exactly as the installed ``torchiid`` script does
(``sys.exit(main())``) with its own stdout, stderr and exit status, and an uncaught exception
printed by the interpreter's own hook. This keeps a few dozen start-ups of torch (about 2 s
each on the development machine) out of the suite. Run as a script, this module is that
process: ``python reliability_harness.py JOBS.json RESULTS.json``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
ENV.pop("TORCHIID_TEST_INTERRUPT", None)


@dataclass
class Run:
    status: int
    stdout: str
    stderr: str

    @property
    def lines(self) -> list[str]:
        """The stderr lines as a terminal shows them: text after the last carriage return."""
        shown = (line.split("\r")[-1].rstrip() for line in self.stderr.split("\n"))
        return [line for line in shown if line.startswith("torchiid")]

    def errors_about(self, name: str) -> list[str]:
        """The ``torchiid: error:`` lines that mention ``name``."""
        return [line for line in self.lines if line.startswith("torchiid: error:") and name in line]


def run_cli(args, cwd, *, env=None, timeout=240, umask=None) -> Run:
    """``python -m torchiid.cli ARGS`` in ``cwd``; returns its status and output."""
    proc = subprocess.run(
        [sys.executable, "-m", "torchiid.cli", *map(str, args)],
        cwd=cwd,
        env={**ENV, **(env or {})},
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout,
        umask=-1 if umask is None else umask,
    )
    return Run(proc.returncode, proc.stdout, proc.stderr)


def run_many(jobs: list[list[str]], cwd, timeout=240) -> list[Run]:
    """Run each command line of ``jobs`` in its own forked process (see the module notes)."""
    with tempfile.TemporaryDirectory() as tmp:
        spec, results = Path(tmp) / "jobs.json", Path(tmp) / "results.json"
        spec.write_text(json.dumps([[str(a) for a in job] for job in jobs]))
        proc = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), str(spec), str(results)],
            cwd=cwd,
            env=ENV,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        if proc.returncode != 0:
            raise AssertionError(f"the job runner failed:\n{proc.stdout}\n{proc.stderr}")
        return [Run(**r) for r in json.loads(results.read_text())]


def _child(argv: list[str], out: str, err: str) -> None:  # pragma: no cover - runs forked
    code = 1
    try:
        for fd, path in ((1, out), (2, err)):
            target = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            os.dup2(target, fd)
            os.close(target)
        from torchiid.cli import main

        sys.argv = ["torchiid", *argv]
        try:
            sys.exit(main())
        except SystemExit as exc:  # what the interpreter does with sys.exit's argument
            if exc.code is None:
                code = 0
            elif isinstance(exc.code, int):
                code = exc.code
            else:
                print(exc.code, file=sys.stderr)
        except BaseException:  # what the interpreter does with an uncaught exception
            sys.excepthook(*sys.exc_info())
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _serve(spec: Path, results: Path) -> None:  # pragma: no cover - a separate process
    # what `torchiid decompose` imports when it has images to decompose, once, before the forks
    import torchiid.cli  # noqa: F401
    import torchiid.collection.job  # noqa: F401
    import torchiid.collection.runner  # noqa: F401
    import torchiid.model  # noqa: F401

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, argv in enumerate(json.loads(spec.read_text())):
            o, e = os.path.join(tmp, f"{i}.out"), os.path.join(tmp, f"{i}.err")
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                _child(argv, o, e)
            _, wait_status = os.waitpid(pid, 0)
            out.append(
                {
                    "status": os.waitstatus_to_exitcode(wait_status),
                    "stdout": Path(o).read_text(errors="replace"),
                    "stderr": Path(e).read_text(errors="replace"),
                }
            )
    results.write_text(json.dumps(out))


if __name__ == "__main__":  # pragma: no cover
    _serve(Path(sys.argv[1]), Path(sys.argv[2]))
