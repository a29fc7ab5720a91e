"""Every fault ``acquire sim`` can inject, through a whole ``acquire run --fake``: the fault is
injected through the simulated cell's fault API (as ``acquire sim``'s stdin does) the moment the
run logs a chosen step; nothing in the run knows. Faults the plan tolerates end in a complete run
with every configuration measured; one that outlasts its allowance fails just its configuration.

Each run costs ~15–40 s of wall time: the per-fault runs are ``slow``; one (drives off, the
fault the issue saw end a run) stays in the default selection.
"""

from __future__ import annotations

import pytest
import yaml

from acquire.plan.schema import load_plan, resolve_configurations

from run_helpers import ROOT, RUN_TIMEOUT_S, faulted_run, small_plan  # noqa: E402 - tests/acquire is on sys.path under pytest

pytestmark = pytest.mark.timeout(RUN_TIMEOUT_S)

#: The example plan's robot (FRI, a fake Sunrise) and bar (NatNet, a fake Motive), 3× real time.
SEQUENCING = {"samples": 5, "settle_window_s": 0.2, "lost_target_wait_s": 5, "robot_fault_wait_s": 30,
              "sensor_fault_wait_s": 30}


def plan_for(tmp_path, base: str = "example.yaml", n: int = 4, allowances: dict | None = None, **sequencing):
    over = {"sequencing": {**SEQUENCING, **sequencing}}
    if allowances is not None:
        cell = yaml.safe_load((ROOT / "fixtures" / "sim" / "default.yaml").read_text())
        cell["robot"] = str((ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml").resolve())
        cell["allowances"] = allowances
        (tmp_path / "cell.yaml").write_text(yaml.safe_dump(cell, sort_keys=False))
        over["fake"] = {"sim_config": str(tmp_path / "cell.yaml"), "time_scale": 3.0}
    return load_plan(small_plan(tmp_path, base, n=n, **over))


def assert_complete(lp, summary, contents) -> None:
    """The run finished with every configuration of the plan measured, once."""
    assert summary.state == "finished", summary.reason
    ids = [s["config_id"] for s in contents.samples]
    assert sorted(ids) == sorted(c.config_id for c in resolve_configurations(lp)), \
        [(e["kind"], e.get("reason")) for e in contents.events if e["kind"] in ("skipped", "failed")]


def suspensions(contents, cause: str) -> list[dict]:
    return [e for e in contents.events if e["kind"] == "suspended" and e.get("cause") == cause]


def test_drives_off_for_two_seconds_suspends_the_run_and_it_completes(tmp_path):
    """Seen: three configurations "move refused: drives not ACTIVE" within 0.2 s → run failed."""
    lp = plan_for(tmp_path, n=3)
    summary, contents, hit = faulted_run(lp, "drives_off", "controller", 2.0, at="moved", nth=2)
    assert hit == ["controller"]
    assert_complete(lp, summary, contents)
    # (on a loaded host the fake Motive may starve too: those suspensions are waited out as well)
    s = next(e for e in suspensions(contents, "device_fault") if "drives not ACTIVE" in " ".join(e["not_ready"]))
    assert s["device"] == "fri"
    resumed = [e for e in contents.events if e["kind"] == "resumed" and e.get("cause") == "device_fault"
               and e["config_id"] == s["config_id"] and e["t"] >= s["t"]]
    assert resumed
    # nothing moved while the drives were off: the next move came after the resume
    moved_after = [e for e in contents.events if e["kind"] == "moved" and e["t"] > s["t"]]
    assert moved_after and moved_after[0]["t"] >= resumed[0]["t"]


@pytest.mark.slow
@pytest.mark.parametrize("fault, device, duration_s, probability, at, cause", [
    ("sensor_stall", "mocap", 2.0, None, "moved", "device_fault"),     # seen: failed after 3 timeouts
    ("beam_break", "mocap", 1.0, None, "moved", "lost_target"),        # seen: skipped 11 ms after suspending
    ("session_drop", "controller", 1.0, None, "moved", None),
    ("session_drop", "mocap", 1.0, None, "moved", None),               # Motive forgets its clients
    ("controller_restart", "controller", None, None, "moved", None),
    ("packet_loss", "mocap", 3.0, 0.3, "moved", None),
])
def test_a_fault_that_passes_is_waited_out_and_the_run_completes(tmp_path, fault, device, duration_s, probability,
                                                                  at, cause):
    lp = plan_for(tmp_path)
    summary, contents, hit = faulted_run(lp, fault, device, duration_s, probability, at=at, nth=2)
    assert hit == [device]
    assert_complete(lp, summary, contents)
    if cause is not None:  # the fault lands while settling: the run must have noticed, and resumed
        assert suspensions(contents, cause), [e["kind"] for e in contents.events]
        assert any(e["kind"] == "resumed" and e.get("cause") == cause for e in contents.events)


@pytest.mark.slow
def test_packet_loss_that_makes_the_joint_state_stale_is_waited_out(tmp_path):
    """Seen: 30 % loss for 3 s → "measured joint state is 208 ms old (allowed 100 ms)" while
    settling, not treated as a device fault → run failed. A cell whose commander allows 15 ms
    (wall) between states meets stale states under 60 % loss."""
    lp = plan_for(tmp_path, allowances={"silence_ms": 300, "state_age_ms": 15})
    summary, contents, hit = faulted_run(lp, "packet_loss", "controller", 3.0, 0.6, at="moved", nth=2)
    assert hit == ["controller"]
    assert_complete(lp, summary, contents)


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["sensor_stall", "session_drop"])
def test_a_tracker_that_stalls_or_drops_its_connection_is_waited_out(tmp_path, fault):
    lp = plan_for(tmp_path, "tracker.yaml", n=3)
    summary, contents, hit = faulted_run(lp, fault, "tracker", 2.0, at="moved", nth=2)
    assert hit == ["tracker"]
    assert_complete(lp, summary, contents)


@pytest.mark.slow
def test_drives_off_longer_than_the_robot_allowance_fails_that_configuration_only(tmp_path):
    """Drives off right after a measurement for 1.2 s of wall time (3.6 s simulated) against
    ``robot_fault_wait_s: 2``: the next configuration's move is refused, it waits 2 s and fails
    with the reason; the one after waits from its own first fault, the drives come back within
    it, and the run goes on and finishes."""
    lp = plan_for(tmp_path, n=3, robot_fault_wait_s=2)  # four configurations
    summary, contents, _ = faulted_run(lp, "drives_off", "controller", 1.2, at="measured", nth=1)
    assert summary.state == "finished", summary.reason
    (failed,) = [e for e in contents.events if e["kind"] == "failed"]
    assert "drives not ACTIVE" in failed["reason"] and "allowed 2 s" in failed["reason"]
    measured = [s["config_id"] for s in contents.samples]
    assert failed["config_id"] not in measured
    assert len(measured) + 1 == len(resolve_configurations(lp))
    assert any(s["t_start"] > failed["t"] for s in contents.samples)  # measured again once the drives were back
