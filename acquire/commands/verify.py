"""``acquire verify``: after the offsets were entered, measure fresh configurations and show what
the robot now does against what the calibration predicted.

Examples::

    acquire verify plan.yaml --result runs/<id>/result.json              # the cell of the plan
    acquire verify plan.yaml --result runs/<id>/result.json --fake       # the plan's simulated cell
    acquire verify plan.yaml --result runs/<id>/result.json --log runs/<v>/<v>.mcap   # score again, move nothing

The plan is the calibration's (its devices, its sequencing and its generated region): the run
measures ``--poses`` new poses of that region with another seed (every feasible IK branch; none
the calibration measured), logs them as any run does (MCAP, resumable with ``--resume``), fits
nothing of the robot — only each sensor's registration and the tool, on the nominal arm, held out
— and writes ``verify.json`` and ``verify.html`` beside the log (``acquire.run.verify``,
``calib.fit.verification``). The console shows the robot as found and now, the measured and the
predicted improvement with its interval, and the verdict.

Why a command and not a plan of its own: a verification is defined by the calibration it checks
(its result, what it entered, its region), so it takes the calibration's plan and result as they
are; the operator writes nothing new, and the fresh configurations cannot be the calibration's.

Exit codes: 0 verified (as predicted, better than predicted, or measured without a prediction);
3 worse than predicted; 1 the run failed or too few configurations were measured to score; 2 bad
input (plan, result, log, output folder), before anything moves; 130 Ctrl-C (the robot stops
safely, the log is closed and resumable).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import typer

from acquire.live.console import display_path

log = logging.getLogger(__name__)

#: Exit code of a verification whose robot does worse than predicted.
EXIT_WORSE = 3


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _calibration_q(result: Path, lp):
    """The joint vectors (k, n) rad the calibration measured, when its log is at hand (else None)."""
    import json

    from acquire.run.verify import calibration_log

    try:
        doc = json.loads(result.read_text(encoding="utf-8"))
        cal_log = calibration_log(result, doc)
        if cal_log is None:
            return None
        from acquire.record.datasets import load_dataset

        return load_dataset(cal_log, lp.model).q_rad
    except (ValueError, OSError) as exc:
        log.warning("the calibration's configurations could not be read (%s): fresh ones are only another seed", exc)
        return None


def _measure(lp, configs, *, fake: bool, out: Optional[Path], resume: Optional[Path], verbose: int):
    """Run ``configs`` without a fit (``acquire run``'s procedure); the run's summary."""
    from acquire.commands.run import StopSafelyOnSignals, _start_simulated_cell, wait_for_end
    from acquire.live.console import configure_console
    from acquire.live.progress import make_progress
    from acquire.run import RunController, RunError

    configure_console(verbose)
    controller = RunController(lp, configs=configs, resume=resume, bus=None, out_dir=out, fit=False)
    try:
        controller.check_output()
    except RunError as exc:
        _fail(str(exc))
    progress = make_progress()
    controller.on_progress = progress.update
    signals = StopSafelyOnSignals(controller).install()
    sim = None
    try:
        if fake:
            sim = _start_simulated_cell(lp, controller)
        controller.start()
        return wait_for_end(controller)
    finally:
        signals.restore()
        progress.close()
        if sim is not None:
            sim.close()


def _load_only(plan: Path):
    """The plan without resolving its configurations (``--log`` moves nothing); exit 2 when bad."""
    from acquire.plan.schema import load_plan

    try:
        return load_plan(plan)
    except (ValueError, OSError) as exc:  # ConfigError is a ValueError
        _fail(str(exc))


def _with_cell(lp, cell: Path, fake: bool):
    """``lp`` whose ``--fake`` cell is ``cell`` (checked as ``acquire run --fake`` checks a plan's)."""
    from dataclasses import replace

    from acquire.commands.fake import check_fake_section
    from acquire.plan.schema import FakeSpec

    if not fake:
        _fail("--cell is the simulated cell of --fake; given --cell without --fake")
    fake_spec = lp.plan.fake or FakeSpec()
    lp = replace(lp, plan=lp.plan.model_copy(update={"fake": fake_spec.model_copy(update={"sim_config": str(cell.resolve())})}))
    try:
        check_fake_section(lp)
    except ValueError as exc:
        _fail(f"--cell {cell}: {exc}")
    return lp


def verify(
    plan: Path = typer.Argument(..., help="The calibration's plan YAML (devices, sequencing, the generated region)."),
    result: Path = typer.Option(..., "--result", help="The calibration's result.json: what was entered, what it predicted."),
    fake: bool = typer.Option(False, "--fake", help="Run against the plan's simulated cell (its controller's mastering "
                                                    "is the cell file's controller.mastering_deg)."),
    cell: Optional[Path] = typer.Option(None, "--cell", help="With --fake: this cell file instead of the plan's "
                                                             "fake.sim_config (e.g. one `acquire sim` saved after 'enter')."),
    poses: Optional[int] = typer.Option(None, "--poses", min=2, help="Fresh candidate poses (default: the plan's n)."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="Seed of the fresh poses (default: the plan's + 1000)."),
    log_path: Optional[Path] = typer.Option(None, "--log", help="Score this verification log again; move nothing."),
    resume: Optional[Path] = typer.Option(None, "--resume", help="Continue the verification run recorded in this log "
                                                                 "(same --poses and --seed)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for the run (default: the plan's output.folder); "
                                                           "with --log, for verify.json (default: beside the log)."),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="Console shows INFO (-v) or DEBUG (-vv) logs too."),
) -> None:
    """Measure fresh configurations after the offsets were entered; compare with the prediction."""
    from acquire.commands.run import _load, plan_argument
    from acquire.run.verify import fresh_configurations, load_result

    if not result.is_file():
        _fail(f"--result {result}: no such file (give the result.json of the calibration whose values were entered)")
    try:
        _, values = load_result(result)
    except ValueError as exc:
        _fail(str(exc))
    plan, _ = plan_argument(plan)
    lp = _load(plan, fake)[0] if log_path is None else _load_only(plan)
    if cell is not None:
        lp = _with_cell(lp, cell, fake)
    if values.refused:
        typer.echo("warning: the result says do not enter: " + "; ".join(values.refused), err=True)
    typer.echo("entered (" + values.source + "): " + (", ".join(f"{a.axis} δ {a.delta_deg:+.4f}°" for a in values.axes)
                                                      or "nothing"))
    for given, name in ((log_path, "--log"), (resume, "--resume")):
        if given is not None and not given.is_file():
            _fail(f"{name} {given}: no such file")
    if log_path is None:
        try:
            configs = fresh_configurations(lp, poses=poses, seed=seed, exclude_q_rad=_calibration_q(result, lp))
        except ValueError as exc:  # ConfigError
            _fail(str(exc))
        if len(configs) < 4:
            _fail(f"{plan}: {len(configs)} fresh configuration(s): too few to score held out (allowed ≥ 4: more --poses)")
        typer.echo(f"{len(configs)} fresh configurations of the plan's region ({configs[0].config_id} …)")
        summary = _measure(lp, configs, fake=fake, out=out, resume=resume, verbose=verbose)
        if summary.log_path is None or summary.measured < 4 or summary.state not in ("finished", "aborted"):
            _fail(f"the verification run measured {summary.measured} configuration(s) ({summary.state}"
                  f"{': ' + summary.reason if summary.reason else ''}): too few to score", summary.exit_code or 1)
        if summary.state == "aborted":
            typer.echo(f"resume with: acquire verify {plan} --result {result} --resume {display_path(summary.log_path)}"
                       + (" --fake" if fake else "") + (f" --poses {poses}" if poses else "") + (f" --seed {seed}" if seed is not None else ""))
            raise typer.Exit(summary.exit_code)
        log_path = summary.log_path
        typer.echo(f"measured {summary.measured}, skipped {summary.skipped}, failed {summary.failed}; "
                   f"log: {display_path(log_path)}")
    from acquire.run.verify import verify_log
    from calib.fit.verification import summary_lines

    try:
        doc, json_path, report = verify_log(log_path, lp, result, out_dir=out)
    except (ValueError, OSError) as exc:
        _fail(str(exc), 1)
    typer.echo(f"prediction: {doc['prediction_from']}")
    for line in summary_lines(doc):
        typer.echo(line)
    typer.echo(f"written: {display_path(json_path)}" + (f", {display_path(report)}" if report else ""))
    if doc["verdict"] == "worse than predicted":
        raise typer.Exit(EXIT_WORSE)


def register(app: typer.Typer) -> None:
    """Add the ``verify`` sub-command to ``app``."""
    app.command("verify")(verify)
