"""Late answers that a stall of the whole test machine does not explain.

The fake controllers of the commander tests are real-time threads that send on their own
schedule, whatever the commander answers. When the packets stop arriving for several cycles, the
controller itself could not run: the machine stalled (on a shared CI host, the hypervisor gives
no CPU for tens of ms), and the answer in flight then was late for the same reason. A late answer
away from any such gap is the exchange's own.
"""

from __future__ import annotations

import numpy as np


def late_outside_stalls(arrived: np.ndarray, latency: np.ndarray, cycle_s: float, stall_cycles: float = 2.0) -> np.ndarray:
    """Indices of the answers later than ``cycle_s`` that are not next to a stall of the controller.

    arrived: (m,) arrival time of each packet, s (``answer_log()``'s column, oldest first).
    latency: (m,) answer latency of each packet, s. cycle_s: the controller's period, s.
    stall_cycles: an arrival gap longer than this many periods is a stall of the controller;
    the packets on both sides of it are excused.
    """
    arrived = np.asarray(arrived, dtype=float)
    latency = np.asarray(latency, dtype=float)
    late = np.flatnonzero(latency > cycle_s)
    gap = np.flatnonzero(np.diff(arrived) > stall_cycles * cycle_s)  # between packet i and i + 1
    near_stall = np.zeros(arrived.size, dtype=bool)
    near_stall[gap] = near_stall[gap + 1] = True
    return late[~near_stall[late]]
