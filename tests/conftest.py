"""Settings for every test process (pytest and its xdist workers import this before the test modules).

OpenBLAS picks its kernels by the CPU it finds (Haswell, SkylakeX, Zen, …), and kernels round differently: the
golden traces (tests/test_golden.py) are bit-for-bit, so every test process uses one kernel set and one thread,
whatever the machine. Set before numpy is first imported.
"""

import os

os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
