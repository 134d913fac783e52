"""cgamap.daemon: the ``cgamap`` command line and the ``cgamapd`` service."""

import os

# Set before anything imports numpy.  Our linear algebra is small (3x3 solves, a few hundred
# segments, sparse graph solves): threaded BLAS buys nothing there and, on a robot's few
# cores shared with the device threads, spins against them (measured on this 2-core machine
# under load: mapping 2.0 -> 2.6 ms per scan with the default threads).  A caller's own
# setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
