"""``acquire fit`` on socket data (``calib.fit.socket``): the fit of a socket file or run, printed
and written; the fit itself and its result document are ``acquire.run.socket_fit``'s (the run's
end-of-run fit uses them too)."""

from __future__ import annotations

from pathlib import Path

import typer

from acquire.run.socket_fit import format_socket_summary, run_socket_fit, write_socket_model
from calib.fit.socket import SocketDataError, SocketDataset, read_socket_csv
from calib.robot.model import RobotModel


def fit_socket_file(path: Path, model: RobotModel, *, method: str, distance_mm: float | None,
                    link_tolerance: tuple[float, float] | None, output: Path | None, model_out: Path | None,
                    compliance: bool = False, dataset: SocketDataset | None = None, force: str | None = None,
                    report: Path | None = None) -> dict:
    """Fit a socket CSV (or ``dataset``, e.g. a socket run's, ``read_socket_run``) by ``method``
    (``run_socket_fit``); print the summary; write the result, the corrected model and, with
    ``report``, the HTML report (``calib.report.report_socket``). Exits 1 when the values must not
    be entered."""
    from calib.fit.result import write_result

    try:
        ds = dataset if dataset is not None else read_socket_csv(path, model.n_joints, distance_mm=distance_mm)
        doc, fit = run_socket_fit(model, ds, method=method, link_tolerance=link_tolerance, compliance=compliance,
                                  force=force)
    except SocketDataError as exc:
        raise typer.BadParameter(str(exc), param_hint="DATA") from exc
    except ValueError as exc:  # an unknown --model
        raise typer.BadParameter(str(exc), param_hint="--model") from exc
    typer.echo(format_socket_summary(doc))
    if model_out is None and output is not None:
        model_out = output.with_name(output.stem + ".model.yaml")
    if model_out is not None:
        doc["model_file"] = str(write_socket_model(model, fit, model_out))
        typer.echo(f"wrote {model_out}")
    if output is not None:
        write_result(output, doc)
        typer.echo(f"wrote {output}")
    if report is not None:
        from calib.report.report_socket import write_socket_report  # the report's modules only when one is asked for

        write_socket_report(report, doc)
        typer.echo(f"wrote {report}")
    if not doc["trusted"]:
        raise typer.Exit(1)
    return doc
