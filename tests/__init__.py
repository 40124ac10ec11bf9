"""The test suite (docs/testing.md).

One BLAS thread per test process, and for the processes the tests start, unless the caller set a
count: the suite runs on both cores (two pytest workers) and OpenBLAS's default of one thread per
core then spins against the other worker. Measured on the models' and the residual loop's tests
with both cores busy: 31-42 s of CPU with the default, 18 s with one thread (D195). This package is
imported before any test module or ``conftest.py``, so before numpy, which reads the variables when
it loads; the command-line tools set the same for themselves (``daror_runtime.cli.limit_blas_threads``).
"""

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")
