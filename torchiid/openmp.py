"""A shorter OpenMP spin-wait for torch's CPU threads, set before torch is first imported.

GNU OpenMP (libgomp, which torch's Linux wheels ship) keeps each worker thread spinning
for ``GOMP_SPINCOUNT`` iterations (300,000 by default, most of a millisecond) after every
parallel region before it sleeps. The pipeline alternates torch operations with its compiled
kernels, which run on other threads (numba's own OpenMP runtime and a small band pool), so
on a machine with few cores the spinning torch threads take the cores those kernels need.
30,000 spins leave those cores to the kernels, with the same results (the documentation's
Benchmarks page, "Threads and OpenMP"). A value the user has set is kept; the setting only
takes effect when ``torchiid`` is imported before ``torch`` (libgomp reads it once, at load),
as the command line does. Other OpenMP runtimes (LLVM's, Intel's) ignore it.
"""

import logging
import os
import sys

#: spin iterations of an idle libgomp thread before it sleeps (libgomp's default: 300,000)
SPIN_COUNT = "30000"

#: whether torch was already loaded (then its OpenMP runtime has read its settings already)
TOO_LATE = "torch" in sys.modules

os.environ.setdefault("GOMP_SPINCOUNT", SPIN_COUNT)
if TOO_LATE and os.environ["GOMP_SPINCOUNT"] == SPIN_COUNT:
    logging.getLogger(__name__).debug(
        "torch was imported before torchiid, so GOMP_SPINCOUNT=%s does not reach torch's "
        "OpenMP threads; import torchiid first or export the variable",
        SPIN_COUNT,
    )
