"""The test suite (docs/testing.md).

One BLAS thread per test process, and for the processes the tests start, unless the caller set a
count: the suite runs on both cores (two pytest workers) and OpenBLAS's default of one thread per
core then spins against the other worker. Measured on the models' and the residual loop's tests
with both cores busy: 31-42 s of CPU with the default, 18 s with one thread (D195). This package is
imported before any test module or ``conftest.py``, so before numpy, which reads the variables when
it loads; the command-line tools set the same for themselves (``daror_runtime.cli.limit_blas_threads``).

JAX's persistent compilation cache, for the test processes and the processes they start (``daror
fit``, the search's workers: the variables are inherited), unless the caller set a folder: the
neural tests compile the same programs in many processes (every ``daror fit`` compiles its network
anew), run after run. The folder is the system's temporary one's ``daror-tests-jax-<uid>``, shared
by the two pytest workers and by later runs: jax's key is the program with its compile options,
XLA flags and jax/jaxlib version, and a hit returns the executable that compiling would give, so no
result changes. Every program is kept however quick to compile; the size bound (256 MB, least
recently used evicted) also makes jax take a file lock around every read and write, so one process
never reads an entry another is still writing. The search's own ``--cache-dir`` (its tests pass
one) takes precedence in its workers.
"""

import os
import tempfile

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.path.join(tempfile.gettempdir(), f"daror-tests-jax-{os.getuid()}")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"
    os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(256 * 1024 * 1024)
