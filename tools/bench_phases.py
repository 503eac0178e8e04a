"""Where a ``torchiid decompose`` process's memory goes, step by step, for one photo.

Usage:
    python tools/bench_phases.py [--size 512] [--photo PATH] [--json FILE]

``tools/bench_peaks.py`` gives a process's two peaks from outside; this tool says which step
reaches them and what glibc's allocator holds there. It runs ``torchiid decompose`` on one
photo (coffee from ``skimage.data``, 3:2, ``--size`` px on the long side, made as for
``tools/bench_steps.py``; or ``--photo``) in a child process, with this checkout's torchiid
first on its path, that adds only a thread reading its own resident memory
(``/proc/self/statm``) about every half millisecond (further apart while the run's Python
code holds the interpreter's lock), and marks the steps: Stage 0's CNN pass and proposals,
then each alternation's shading solve, the reflectance stage's terms (its colour features
and weights) and its Split-Bregman solve.

For each step it prints the resident memory when the step starts and its peak, and glibc's
allocator (``mallinfo2``) at the first reading of that peak (at the step's start for a step
whose memory only falls): the bytes in use and the bytes free inside its heap, and the
address space of the buffers it maps one by one (those above its mmap threshold, such as
onnxruntime's arena and the reflectance stage's weights: reserved, not all of it resident).
Freeing a buffer inside the heap need not lower the resident memory: the free bytes are
memory no tensor uses, freed buffers below allocations still in use, which the allocator
does not give back by itself (``malloc_trim`` can). The last row is the rest of the run
(start-up, the steps between, the outputs). Linux only; the allocator's columns need glibc
2.33 or later. Printed: a Markdown table in MiB.

The marks wrap a few internal functions by name (:mod:`torchiid.pipeline.alternation`'s
``solve_shading``, :mod:`torchiid.stages.reflectance`'s ``assemble_reflectance_terms`` and
``split_bregman``, selective search, the ONNX extractor's call). The child shares one
allocator arena among its threads before the sampling thread starts, as the command does
before its work; the thread and the marks add about 2 MiB.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

MIB = 1 << 20
REST = "the rest (start-up, between the steps, outputs)"


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost"
        ).split()
    ]


def heap_reader() -> Callable[[], tuple[float, float, float]] | None:
    """``() -> (MiB in use, MiB free, MiB mapped)`` of glibc's allocator, or ``None``.

    In use and free: inside its heap; mapped: the buffers it maps one by one (above its
    mmap threshold). ``None`` without ``mallinfo2`` (glibc before 2.33, or another C library).
    """
    try:
        libc = ctypes.CDLL(None)
        info = libc.mallinfo2
    except (OSError, AttributeError):
        return None
    info.restype = _MallInfo2

    def read() -> tuple[float, float, float]:
        m = info()
        return m.uordblks / MIB, m.fordblks / MIB, m.hblkhd / MIB

    return read


class PhaseRecorder:
    """The resident memory at the start and the peak of each named step, in order.

    ``rss`` reads the resident memory in MiB; ``heap`` (optional) reads glibc's allocator at
    the first reading of each step's peak (at its start, for a step whose memory only falls).
    Steps are entered with :meth:`enter`; :meth:`sample` (the sampling thread's body, one
    reading) charges a reading to the step running, or to :data:`REST`. A lock keeps a
    reading and the step it is charged to together, whichever thread takes it.
    """

    def __init__(
        self,
        rss: Callable[[], float],
        heap: Callable[[], tuple[float, float, float]] | None = None,
    ) -> None:
        self.rss, self.heap = rss, heap
        self.current = REST
        self.rows: dict[str, dict[str, float | None]] = {}
        self._lock = threading.Lock()
        self._start(REST)

    def _read_heap(self, row: dict[str, float | None]) -> None:
        if self.heap is not None:
            row["in_use"], row["free"], row["mapped"] = self.heap()

    def _start(self, name: str) -> None:
        if name not in self.rows:
            now = self.rss()
            self.rows[name] = dict(start=now, peak=now, in_use=None, free=None, mapped=None)
            self._read_heap(self.rows[name])

    def enter(self, name: str) -> None:
        with self._lock:
            self._start(name)
            self.current = name

    def leave(self) -> None:
        with self._lock:
            self.current = REST

    def sample(self) -> None:
        with self._lock:
            row = self.rows[self.current]
            value = self.rss()
            if value > row["peak"]:  # type: ignore[operator]
                row["peak"] = value
                self._read_heap(row)

    def mark(self, label: str, fn: Callable, numbered: bool = True) -> Callable:
        """``fn`` wrapped so that each call is a step: ``label`` and the call's number."""
        calls = [0]

        def wrapped(*args, **kwargs):
            calls[0] += 1
            self.enter(f"{label} {calls[0]}" if numbered else label)
            try:
                return fn(*args, **kwargs)
            finally:
                self.sample()
                self.leave()

        return wrapped

    def table(self) -> list[dict[str, float | str | None]]:
        """The steps in the order they started, :data:`REST` last."""
        order = [n for n in self.rows if n != REST] + [REST]
        return [{"step": n, **self.rows[n]} for n in order]


def _statm_reader() -> Callable[[], float]:
    page = os.sysconf("SC_PAGE_SIZE")
    fd = os.open("/proc/self/statm", os.O_RDONLY)
    return lambda: int(os.pread(fd, 128, 0).split()[1]) * page / MIB


def _child(photo: Path, out: Path, report: Path) -> None:
    """Decompose ``photo`` as ``torchiid decompose`` does, recording the steps' memory."""
    from torchiid.core.memory import share_one_malloc_arena

    # as the command does, but before the sampling thread's first allocation: a thread that
    # allocated earlier would keep an arena of its own, which the run's threads then share
    share_one_malloc_arena()
    rec = PhaseRecorder(_statm_reader(), heap_reader())
    stop = threading.Event()

    def sampler() -> None:
        while not stop.is_set():
            rec.sample()
            time.sleep(0.0005)

    thread = threading.Thread(target=sampler, name="bench-phases", daemon=True)
    thread.start()
    import torchiid.features.proposals as proposals
    import torchiid.pipeline.alternation as alternation
    import torchiid.stages.reflectance as reflectance
    from torchiid.cli import main
    from torchiid.features.onnx_backend import OnnxFeatureExtractor

    extractor_call = OnnxFeatureExtractor.__call__
    OnnxFeatureExtractor.__call__ = rec.mark("Stage 0: CNN pass", extractor_call, False)
    proposals.selective_search = rec.mark("Stage 0: proposals", proposals.selective_search, False)
    alternation.solve_shading = rec.mark("shading solve", alternation.solve_shading)
    reflectance.assemble_reflectance_terms = rec.mark(
        "reflectance terms", reflectance.assemble_reflectance_terms
    )
    reflectance.split_bregman = rec.mark("reflectance solve", reflectance.split_bregman)
    status = main(["decompose", str(photo), "-o", str(out), "-q"], own_process=True)
    stop.set()
    thread.join()
    rec.sample()
    if status != 0:  # the command has said why on stderr, which the parent reads
        raise SystemExit(status)
    with open("/proc/self/status") as status_file:
        hwm = [int(x.split()[1]) / 1024 for x in status_file if x.startswith("VmHWM")]
    report.write_text(json.dumps({"rows": rec.table(), "process_peak": hwm[0]}))


def _mib(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.0f}"


def render(result: dict, title: str) -> str:
    """The Markdown table of a child's report."""
    lines = [
        title,
        "| step | resident at its start | its peak | at the peak: heap in use | heap free "
        "| mapped by malloc (reserved) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in result["rows"]:
        cells = [_mib(row[k]) for k in ("start", "peak", "in_use", "free", "mapped")]
        lines.append(f"| {row['step']} | " + " | ".join(cells) + " |")
    lines.append(f"| the whole process (VmHWM) | | {result['process_peak']:.0f} | | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512, help="long side of the 3:2 photo (px)")
    ap.add_argument("--photo", type=Path, help="decompose this file instead")
    ap.add_argument("--json", type=Path, help="also write the measurements to this JSON file")
    ap.add_argument("--child", nargs=3, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        _child(*args.child)
        return
    if args.photo is not None and not args.photo.is_file():
        raise SystemExit(f"bench_phases.py: --photo {args.photo}: no such file")
    if args.photo is None and args.size < 90:  # torchiid decomposes photos of 60 px or more
        raise SystemExit(f"bench_phases.py: --size {args.size}: the 3:2 photo needs 90 px or more")
    if args.json is not None and not args.json.resolve().parent.is_dir():
        raise SystemExit(f"bench_phases.py: --json {args.json}: its folder does not exist")
    if not Path("/proc/self/statm").exists():
        raise SystemExit("bench_phases.py: reads /proc/self/statm: Linux only")
    root = Path(__file__).resolve().parents[1]
    # the child measures this checkout's torchiid, whatever else is installed
    paths = [str(root), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
    with tempfile.TemporaryDirectory(prefix="bench-phases-") as tmp:
        work = Path(tmp)
        photo = args.photo.resolve() if args.photo is not None else None
        if photo is None:
            from bench_bell import make_photos

            (photo, *_) = make_photos(work / "photos", args.size, round(args.size * 2 / 3))
        report = work / "report.json"
        cmd = [sys.executable, __file__, "--child", str(photo), str(work / "out"), str(report)]
        run = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        if run.returncode != 0:
            lines = run.stderr.strip().splitlines() or ["(no output)"]
            said = [x for x in lines if x.startswith("torchiid: error:")] or lines[-1:]
            raise SystemExit(f"bench_phases.py: the measured process failed: {said[0]}")
        result = json.loads(report.read_text())
    title = f"`torchiid decompose` on {photo.name}: resident memory per step, MiB"
    print(render(result, title))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
