"""The test helper that excuses late answers in a stall of the whole machine, and only those."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from late_answers import late_outside_stalls  # noqa: E402

CYCLE = 0.004


def stream(n: int = 100) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(n) * CYCLE, np.full(n, 0.0003)


def test_late_answers_in_a_steady_stream_are_the_exchanges_own():
    arrived, latency = stream()
    latency[[10, 50, 51]] = 0.006
    np.testing.assert_array_equal(late_outside_stalls(arrived, latency, CYCLE), [10, 50, 51])


def test_the_answers_beside_a_stall_of_the_controller_are_excused_and_no_others():
    arrived, latency = stream()
    arrived[41:] += 0.030  # the controller sent nothing for 34 ms: the machine stalled
    latency[[40, 41, 60]] = 0.031, 0.005, 0.006  # the answer in flight, the next one, and one later
    np.testing.assert_array_equal(late_outside_stalls(arrived, latency, CYCLE), [60])


def test_a_late_answer_alone_does_not_make_a_stall():
    arrived, latency = stream()
    arrived[31:] += 0.003  # one period 1.75 cycles long: jitter, not a stall
    latency[30] = 0.005
    np.testing.assert_array_equal(late_outside_stalls(arrived, latency, CYCLE), [30])
