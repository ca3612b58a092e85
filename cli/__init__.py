"""The `macb` command: `cli.main` assembles the parser from one module per command group.

Thread settings are chosen here, when the package is first imported and so before numpy
or torch load: every process of the platform shares 2 cores with the others, and BLAS
threads fighting torch's threads slow every process (benchmarks/bench_e2e.py's `trainer`
variant, numpy's default BLAS threads, against `trainer-blas1`). `--threads` still sets
torch's own.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
