"""Kill `acquire run` at random moments (SIGKILL), resume from its own log, lose nothing."""

from __future__ import annotations

import random
import signal
import time
from collections import Counter

import pytest

from acquire.plan.schema import load_plan, resolve_configurations
from acquire.record.recorder import RunLogError, read_run

from run_helpers import RUN_TIMEOUT_S, aborted_run, fake_controller, popen, run_logs, small_plan, wait_for_run  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S)


def outcomes(contents) -> tuple[Counter, set]:
    """(sample count per config id, ids ended by a skip/failure event)."""
    counts = Counter(s["config_id"] for s in contents.samples)
    ended = {e["config_id"] for e in contents.events if e["kind"] in ("skipped", "failed")}
    return counts, ended


def wait_for_samples(folder, n: int, timeout: float):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        logs = run_logs(folder)
        if logs and len(read_run(logs[0]).samples) >= n:
            return logs[0]
        time.sleep(0.1)
    return None


def wait_for_starts(log, n: int, timeout: float) -> bool:
    """Until the log holds ``n`` run_started events (a resumed process has opened its devices
    and its segment): a kill is then a kill of a running run, however slow the machine."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if sum(1 for e in read_run(log).events if e["kind"] == "run_started") >= n:
                return True
        except RunLogError:  # the new segment is being created
            pass
        time.sleep(0.1)
    return False


# ~60 s of simulated runs killed and resumed: the slow selection (resume after an abort and after a
# controller drop stay in the default one)
@pytest.mark.slow
@pytest.mark.parametrize("seed", [7])
def test_sigkill_at_random_moments_then_resume_measures_every_configuration_once(tmp_path, seed):
    rng = random.Random(seed)
    plan = small_plan(tmp_path, n=8, sequencing={"samples": 5, "settle_window_s": 0.2}, fake={"time_scale": 6.0})
    configs = {c.config_id for c in resolve_configurations(load_plan(plan))}
    args = ("run", str(plan), "--fake", "--no-bus", "--no-fit")

    # 1st kill: after the first sample appears plus a random delay (mid-move, mid-settle or mid-measure)
    proc = popen(*args)
    log = wait_for_samples(tmp_path / "runs", 1, 60)
    assert log is not None, proc.stderr.read() if proc.poll() is not None else "no sample within 60 s"
    time.sleep(rng.uniform(0.0, 1.5))
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    first = read_run(log)
    killed_after = len(first.samples)
    assert killed_after >= 1

    # 2nd kill: a resumed run killed again at a random moment after it started running
    proc = popen(*args, "--resume", str(log))
    assert wait_for_starts(log, 2, 90), proc.stderr.read() if proc.poll() is not None else "resume did not start in 90 s"
    time.sleep(rng.uniform(0.5, 2.5))
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)

    # final resume runs to the end
    proc = popen(*args, "--resume", str(log))
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err[-3000:]
    contents = read_run(log)
    assert contents.complete
    assert len(contents.files) >= 2  # the original and its resume segments
    counts, ended = outcomes(contents)
    assert max(counts.values()) == 1, [c for c, k in counts.items() if k > 1]  # nothing duplicated
    assert set(counts) | ended == configs  # nothing lost
    assert len(counts) >= 0.8 * len(configs)
    assert sum(1 for e in contents.events if e["kind"] == "run_started") == 3


def test_resume_after_an_abort_continues_and_refuses_another_plan(tmp_path):
    plan = small_plan(tmp_path, n=6, sequencing={"samples": 5, "settle_window_s": 0.2}, fake={"time_scale": 6.0})
    lp = load_plan(plan)
    configs = {c.config_id for c in resolve_configurations(lp)}

    first = aborted_run(lp, 3)
    assert first.state == "aborted" and first.exit_code != 0
    recorded = read_run(first.log_path)
    done_before = {s["config_id"] for s in recorded.samples}
    assert len(done_before) >= 3

    other = small_plan(tmp_path, n=5, name="other.yaml")
    rc_other = fake_controller(load_plan(other), resume=first.log_path, fit=False)
    rc_other.start()
    refused = wait_for_run(rc_other)
    assert refused.state == "failed" and "different plan" in refused.reason

    rc2 = fake_controller(lp, resume=first.log_path, fit=False)
    rc2.start()
    second = wait_for_run(rc2)
    assert second.state == "finished", second.reason
    contents = read_run(first.log_path)
    counts, ended = outcomes(contents)
    assert max(counts.values()) == 1
    assert set(counts) | ended == configs
    started = [e for e in contents.events if e["kind"] == "run_started"]
    assert started[-1]["resumed"] is True
    assert not set(started[-1]["order"]) & done_before  # nothing recorded was measured again


@pytest.mark.slow  # ~50 s: waiting faults out is test_run_faults.py's drives-off run (default), resuming test_resume_after_an_abort's
def test_an_fri_drop_is_waited_out_and_failed_configurations_are_measured_again_on_resume(tmp_path):
    """The kill/fault study of issue 11: the FRI session drops mid-run (the robot application
    restarts its overlay) → the run suspends, retries and measures that configuration; the
    drives go off → moves are refused before moving, three in a row end the run; the drives come
    back → ``--resume`` measures the failed configurations again, each exactly once."""
    plan = small_plan(tmp_path, n=8, sequencing={"samples": 5, "settle_window_s": 0.2, "robot_fault_wait_s": 2},
                      fake={"time_scale": 4.0})  # drives off for good: each configuration waits 2 s, then fails
    lp = load_plan(plan)
    configs = {c.config_id for c in resolve_configurations(lp)}
    injected = []

    def faults(status):
        cell = rc.sim
        if cell.launch is None:
            return  # before the devices are up, or after they closed
        if status["measured"] >= 2 and "drop" not in injected:
            injected.append("drop")
            cell.launch.inject("session_drop", "controller")
        elif status["measured"] >= 4 and "drives" not in injected:
            injected.append("drives")
            cell.launch.inject("drives_off", "controller", 3600.0)  # for good (this cell closes after the run)

    rc = fake_controller(lp, on_progress=faults, fit=False)
    rc.start()
    first = wait_for_run(rc)
    assert first.state == "failed" and "fix it and resume the run" in first.reason, first.reason
    contents = read_run(first.log_path)
    kinds = [e["kind"] for e in contents.events]
    failed = {e["config_id"] for e in contents.events if e["kind"] == "failed"}
    assert len(failed) == 3 and all("drives not ACTIVE" in e["reason"] for e in contents.events
                                    if e["kind"] == "failed")
    measured_first = {s["config_id"] for s in contents.samples}
    assert len(measured_first) >= 4  # the configuration hit by the drop was measured after all
    # the session drop mid-move was waited out (a suspension) or had passed at once (a retry)
    assert "retry" in kinds or any(e["kind"] == "resumed" and e.get("cause") == "device_fault" for e in contents.events)
    assert all("still not ready after" in e["reason"] for e in contents.events if e["kind"] == "failed")

    rc2 = fake_controller(lp, resume=first.log_path, fit=False)
    rc2.start()
    second = wait_for_run(rc2)
    assert second.state == "finished", second.reason
    contents = read_run(first.log_path)
    counts, _ = outcomes(contents)
    assert set(counts) == configs and max(counts.values()) == 1
    assert failed <= set(counts)  # measured again on resume
