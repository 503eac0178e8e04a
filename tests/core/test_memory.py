import os
import subprocess
import sys

import pytest

CODE = "from torchiid.core.memory import undo_malloc_trim_threshold as u; print(u())"


def _run(env_extra):
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", CODE], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc only")
def test_thresholds_are_set_only_where_dask_set_the_variable():
    assert _run({"MALLOC_TRIM_THRESHOLD_": "65536"}) == "True"
    assert _run({}) == "False"
