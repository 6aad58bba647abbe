"""Test-session settings.

OpenBLAS threads only add hand-offs on the estimator's 10 x 10 matrices, and on a busy machine
a hand-off can cost milliseconds (measured: 8 ms instead of 20 us per filter update with two
threads while other processes ran). Must be set before numpy is first imported.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
