"""tools/bell2014_port.py: the Python 3 rewriting, the patches, and the port itself when present.

The rewriting is tested on small strings. The port of Bell et al.'s repository needs a copy of
it: ``BELL2014_SOURCE`` (an extracted copy or its bare git directory) for the rewriting of the
real files, ``BELL2014_PORT`` (a folder made by ``prepare``, extension built) for a solve; each
test skips without its variable.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("bell2014_port", ROOT / "tools/bell2014_port.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bell2014_port"] = module
    spec.loader.exec_module(module)
    yield module
    del sys.modules["bell2014_port"]


@pytest.mark.parametrize(
    ("before", "after"),
    [
        ('print "a"', 'print("a")'),
        ("    print 'x:', x", "    print('x:', x)"),
        ('print "%s" % (a, b)', 'print("%s" % (a, b))'),
        ("print", "print()"),
        ("print x,", "print(x, end=' ')"),
        ("print('already')", "print('already')"),
        ("print ('spaced %s' % (", "print ('spaced %s' % ("),
        ("for i in xrange(n):", "for i in range(n):"),
        ("for k, v in d.iteritems():", "for k, v in d.items():"),
        ("d.itervalues()", "d.values()"),
        ("except ValueError, e:", "except ValueError as e:"),
        ("import cPickle", "import pickle"),
        ("x = np.float(y); a.astype(np.float)", "x = np.float64(y); a.astype(np.float64)"),
        ("np.float32(1); np.int_(2); np.bool_(0)", "np.float32(1); np.int_(2); np.bool_(0)"),
        ("m.astype(np.bool, copy=True)", "m.astype(np.bool_, copy=True)"),
        ("dtype=np.int)", "dtype=np.int_)"),
        ("from distutils.core import setup", "from setuptools import setup"),
        ("from distutils.extension import Extension", "from setuptools import Extension"),
        (
            "from scipy.ndimage.filters import gaussian_filter",
            "from scipy.ndimage import gaussian_filter",
        ),
        ("a = b / c  # no integer division here", "a = b / c  # no integer division here"),
    ],
)
def test_rewrite_python2_lines(tool, before, after):
    text, notes = tool.rewrite_python2(before)
    assert text == after
    assert bool(notes) == (before != after)


def test_rewrite_keeps_other_lines_and_numbers_notes(tool):
    src = "import os\n\n\ndef f(n):\n    for i in xrange(n):\n        print i\n    return n\n"
    text, notes = tool.rewrite_python2(src)
    assert text == src.replace("xrange", "range").replace("print i", "print(i)")
    assert notes == ["line 5: xrange", "line 6: print statement"]


def test_implicit_relative_imports_only_for_siblings(tool):
    siblings = frozenset({"judgements", "energy"})
    src = "from judgements import H\nimport energy\nimport numpy\nfrom os import path\n"
    text, notes = tool.rewrite_python2(src, siblings)
    assert text.splitlines() == [
        "from .judgements import H",
        "from . import energy",
        "import numpy",
        "from os import path",
    ]
    assert len(notes) == 2


def test_print_redirection_is_refused(tool):
    with pytest.raises(tool.PortError, match="redirection"):
        tool.rewrite_python2('print >>sys.stderr, "x"')


def test_siblings_of_a_package_module(tool):
    files = dict.fromkeys(
        [
            "pkg/__init__.py",
            "pkg/a.py",
            "pkg/b.py",
            "pkg/sub/__init__.py",
            "pkg/sub/c.py",
            "top.py",
        ],
        b"",
    )
    assert tool._siblings("pkg/a.py", files) == {"a", "b", "sub"}
    assert tool._siblings("pkg/sub/c.py", files) == {"c"}
    assert tool._siblings("top.py", files) == frozenset()


def test_apply_patches_once_each(tool):
    text, notes = tool.apply_patches("a = f(x)\n", [("f(x)", "g(x)", "why")], "m.py")
    assert text == "a = g(x)\n"
    assert notes == ["patch: why"]
    for source in ("a = h(x)\n", "f(x); f(x)\n"):
        with pytest.raises(tool.PortError, match="m.py"):
            tool.apply_patches(source, [("f(x)", "g(x)", "why")], "m.py")


def test_every_patch_says_why(tool):
    for name, patches in tool.PATCHES.items():
        assert name.endswith(".py")
        for old, new, why in patches:
            assert old and old != new and why


def test_prepare_refuses_another_repository(tool, tmp_path):
    (tmp_path / "src").mkdir()
    with pytest.raises(tool.PortError, match="neither"):
        tool.prepare(tmp_path / "src", tmp_path / "port", build=False)
    (tmp_path / "dst").mkdir()
    (tmp_path / "src" / "bell2014").mkdir()
    (tmp_path / "src" / "bell2014" / "solver.py").write_text("x = 1\n")
    with pytest.raises(tool.PortError, match="missing bell2014/density.py"):
        tool.prepare(tmp_path / "src", tmp_path / "port", build=False)
    assert not (tmp_path / "port").exists()
    for name in tool.PATCHES:
        (tmp_path / "src" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "src" / name).write_text("")
    with pytest.raises(tool.PortError, match="not a port"):
        tool.prepare(tmp_path / "src", tmp_path / "dst", build=False)
    with pytest.raises(tool.PortError, match="expected"):
        tool.prepare(tmp_path / "src", tmp_path / "port", build=False)


def test_load_refuses_a_folder_that_is_not_a_port(tool, tmp_path):
    with pytest.raises(tool.PortError, match="not a port"):
        tool.load(tmp_path)


@pytest.mark.skipif(not os.environ.get("BELL2014_SOURCE"), reason="BELL2014_SOURCE not set")
def test_prepare_rewrites_the_repository(tool, tmp_path):
    notes = tool.prepare(os.environ["BELL2014_SOURCE"], tmp_path / "port", build=False)
    for path in (tmp_path / "port").rglob("*.py"):
        text = path.read_text()
        compile(text, str(path), "exec")  # Python 3 syntax
        assert "xrange" not in text and ".iteritems()" not in text and "cPickle" not in text
    for name, patches in tool.PATCHES.items():
        assert sum(n.startswith(f"{name}: patch:") for n in notes) == len(patches)
    assert (tmp_path / "port" / "PORTED.txt").read_text().count("\n") == len(notes) + 2


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("BELL2014_PORT"), reason="BELL2014_PORT not set")
def test_port_solves_a_masked_image(tool):
    bell = tool.load(os.environ["BELL2014_PORT"])
    h, w = 40, 60
    albedo = np.where(np.arange(w)[None, :, None] < 30, [0.6, 0.3, 0.2], [0.2, 0.5, 0.7])
    image = albedo * np.linspace(0.3, 1.0, h)[:, None, None] * np.ones((h, w, 1))
    mask = np.zeros((h, w), bool)
    mask[5:35, 5:55] = True
    params = bell.params.IntrinsicParameters()
    params.fixed_seed, params.n_iters, params.logging = True, 3, True
    with contextlib.redirect_stdout(io.StringIO()) as log:
        # logging mode asserts that splitting the label clusters leaves the layers unchanged
        r, s, _ = bell.solver.IntrinsicSolver(
            bell.input.IntrinsicInput(image, mask), params
        ).solve()
    assert "split_label_clusters" in log.getvalue()
    assert r.shape == (h, w, 3) and s.shape == (h, w)
    np.testing.assert_allclose(r[mask] * s[mask][:, None], image[mask], rtol=1e-9)
    assert not r[~mask].any() and not s[~mask].any()
