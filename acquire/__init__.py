"""The cell-PC application: CLI, plan schema, sequencer, Zenoh bus, MCAP recorder, daemon."""

import os as _os

# One BLAS thread unless the user says otherwise: our matrices are small (tens of columns), so
# threading gains nothing, while idle BLAS threads spin and steal the core that the robot's
# real-time exchange needs (measured: a 6000×47 QR took 25× longer with 2 threads on a loaded
# 2-core machine). Only effective before numpy is first imported; override with the variables.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
