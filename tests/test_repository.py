"""The repository speaks of the software as it is: no word about how it was developed.

Its history is told in versions (``CHANGELOG.md``). Every tracked text file is searched for the
words of a development log: numbered stops or steps of work, sessions of work, issue numbers.
A solver's "stop" or "step" followed by a quantity (``log step 0.1``, ``stops at its cap``) is
technical language and does not match.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: binary files, never searched
BINARY = {".jpg", ".jpeg", ".png", ".exr", ".npy", ".onnx", ".gz", ".mp4", ".pth"}

DEVELOPMENT_WORDS = re.compile(
    r"""
    \bstops?[ -]?\d+(?![\d.])              # a numbered stop of work, a range of them
    | \b(?:before|after|since|until|at)\ stop\b
    | \b(?:this|earlier|previous|next|last)\ stops?\b
    | \bsessions?\ \d+
    | \bwork(?:ing)?\ sessions?\b
    | \bissues?\ \#?\d+
    | \b(?:development|work|tuning)\ step\ \d+
    | \bstep\ \d+(?![\d.])\ of\ (?:the\ )?(?:work|development|project)
    """,
    re.IGNORECASE | re.VERBOSE,
)


def _tracked_text_files() -> list[Path]:
    try:
        run = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60
        )
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    paths = [ROOT / p for p in run.stdout.decode().split("\0") if p]
    return [p for p in paths if p.suffix.lower() not in BINARY and p.is_file()]


def test_no_development_words_in_tracked_files():
    hits = []
    for path in _tracked_text_files():
        data = path.read_bytes()
        if b"\0" in data:
            continue
        text = data.decode("utf-8", errors="replace")
        for number, line in enumerate(text.splitlines(), 1):
            for match in DEVELOPMENT_WORDS.finditer(line):
                hits.append(f"{path.relative_to(ROOT)}:{number}: {match.group(0)!r}")
    assert not hits, "development words (history belongs in CHANGELOG.md):\n" + "\n".join(hits)


@pytest.mark.parametrize(
    "text",
    [
        "before st|op 31",
        "st|op-25 figures",
        "st|ops 20–32",
        "St|op 28: the gap",
        "iss|ue 11",
        "iss|ue #12",
        "a working sess|ion",
        "sess|ion 3",
        "the next st|op",
    ],
)
def test_the_search_finds_development_words(text):
    # each example is cut by "|" so that this file, which the search also reads, holds none
    assert DEVELOPMENT_WORDS.search(text.replace("|", ""))


@pytest.mark.parametrize(
    "text",
    [
        "log step 0.1 > 0.075",
        "stopped at its cap of 100",
        "stops at its safety cap",
        "the ONNX session is cached",
        "start_new_session=True",
        "a step of 0.5 in log-intensity",
        "the first step",
        "stop_on_gap = True",
    ],
)
def test_the_search_leaves_technical_words_alone(text):
    assert not DEVELOPMENT_WORDS.search(text)
