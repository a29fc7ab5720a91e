"""Kinematics, inverse kinematics, pose plans, registration, fitters, metrics and reports.

Pure numpy/scipy (plus pydantic and PyYAML for model files): ``calib`` never imports
``drivers`` or ``acquire``.

Units, stated once for the whole package: lengths in **millimetres**, angles in **radians**,
joint angles in the **controller's axis convention** (the numbers the robot's pendant shows,
converted to radians). Files and the command line use millimetres and degrees.

One sub-package (wing) per pipeline stage, each importing only the ones before it:
``io`` → ``robot`` → ``measure`` → ``ik`` → ``plan`` → ``fit`` → ``report`` (README, "Layout";
checked by ``tests/test_layers.py``).
"""

import os as _os

# One BLAS thread unless the user says otherwise: our matrices are small (tens of columns), so
# threading gains nothing, while idle BLAS threads spin and steal the core that the robot's
# real-time exchange needs (measured: a 6000×47 QR took 25× longer with 2 threads on a loaded
# 2-core machine). Only effective before numpy is first imported; override with the variables.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
