"""One measurement run: from a loaded plan and a cell's description to a closed log and a result.

The modules, in the order a run uses them:

- ``controller`` — ``RunController``: the run's thread and its control surface (start, pause,
  resume, abort, confirm, status, wait) and the loop over the configurations;
- ``state`` — ``RunState``: the state machine and the counters, behind one lock;
- ``prepare`` — the output folder check, what a resumed log leaves to do, the run id, the log;
- ``devices`` — opening and closing the commander and sensors through a
  ``drivers.cell.CellDescription`` (``plan_cell``: a real cell from its plan);
- ``procedure`` — ``ConfigurationRunner``: move, settle, measure, record one configuration,
  the lost-target suspension and the registration estimate;
- ``publish`` — ``RunPublisher``: events and records to the log, the bus and the display;
- ``tap`` — ``JointStateTap``: the robot's joint states streamed into the log;
- ``ending`` — the end of a run and the hand-off to the fitter; ``fitting`` — the fit itself;
- ``summary`` — ``RunSummary``, ``RunError``, the states.
"""

from acquire.run.controller import FIRST_STATE_TIMEOUT_S, MAX_CONSECUTIVE_FAILURES, RunController
from acquire.run.devices import RunDevices, open_commander, open_sensor, plan_cell
from acquire.run.fitting import fit_run_log, fit_socket_run_log
from acquire.run.prepare import SENSOR_RATE_HZ, make_run_id, plan_settings
from acquire.run.summary import STATES, TERMINAL, RunError, RunSummary
from acquire.run.tap import JointStateTap

__all__ = [
    "FIRST_STATE_TIMEOUT_S", "MAX_CONSECUTIVE_FAILURES", "RunController", "RunDevices", "open_commander",
    "open_sensor", "plan_cell", "fit_run_log", "fit_socket_run_log", "SENSOR_RATE_HZ", "make_run_id",
    "plan_settings", "STATES", "TERMINAL", "RunError", "RunSummary", "JointStateTap",
]
