"""Suite-wide settings.

One BLAS thread in every test process and in the processes tests start (set before numpy is
loaded: the environment is read once, when OpenBLAS starts). The fits here are small — tens of
parameters — where threads buy nothing, and on a shared, loaded machine OpenBLAS's threads fight
for the same cores: beside four CPU hogs the compliance coverage study
(``tests/calib/test_gravity.py``) took 84.6 s with the default threads and 30.4 s with one, and
two suites run at once drove it past its 240 s timeout. A value already set is kept.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
