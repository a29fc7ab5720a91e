"""The end of a run: stop the robot on an abort, the link's figures and the last event into the
log, close the devices and the log, then hand the log to the fitter (``fitting.fit_run_log``).

A run asked for a result that has none (nothing measured, the fit failed) ends ``failed`` with
the reason, not ``finished``: the operator must not read "finished" as "calibrated".
"""

from __future__ import annotations

import logging
import time

from drivers.errors import DriverError

log = logging.getLogger(__name__)


def log_link(commander, event) -> None:
    """The real-time link over the run into the log (event ``link``): cycles, late answers,
    answer latency p50/p99/max (µs, over the last ``window`` cycles), missing and malformed
    packets, the exchange's scheduling — how the exchange kept its deadline on this PC."""
    stats = getattr(commander, "link_stats", None)
    if not callable(stats):
        return
    try:
        st = stats()
    except DriverError as exc:
        log.warning("link figures: %s", exc)
        return
    event(
        "link", packets=st.packets, window=st.window, late_answers=st.late_answers,
        latency_p50_us=round(st.latency_p50_s * 1e6, 1), latency_p99_us=round(st.latency_p99_s * 1e6, 1),
        latency_max_us=round(st.latency_max_s * 1e6, 1), gaps=st.gaps, malformed=st.malformed,
        restarts=st.restarts, realtime=st.realtime, notes=list(st.notes),
    )
    if st.late_answers:
        log.warning("%s: %d late real-time answer(s) in this run (%s)", getattr(commander, "name", "commander"),
                    st.late_answers, "; ".join(st.report()[:2]))


def finish(ctl, cell_seconds: float):
    """End the run of ``ctl`` (a ``RunController`` whose loop has stopped); returns its
    ``RunSummary`` with the fit when one was asked for and made."""
    from acquire.run.fitting import fit_run_log

    state, pub = ctl.state, ctl.pub
    aborted = state.aborting.is_set()
    commander = ctl.devices.commander if ctl.devices is not None else None
    if aborted:
        state.set("stopping")
        if commander is not None:
            try:
                commander.stop()
            except DriverError as exc:
                log.warning("stop: %s", exc)
        log_link(commander, pub.event)
        pub.event("aborted", reason=state.reason)
    else:
        log_link(commander, pub.event)
        pub.event("run_finished", measured=state.measured, skipped=state.skipped, failed=state.failed)
    ctl.teardown()
    ctl.measurements_over.set()
    end = "aborted" if aborted else "finished"
    summary = state.summary()
    summary.cell_seconds = cell_seconds
    summary.adaptive = getattr(ctl, "adaptive_summary", None)
    reason = state.reason if aborted else ""
    if not aborted and ctl.fit_enabled and state.log_path is not None:
        if state.measured == 0:
            reason = (f"no result: none of the {state.total} configurations was measured "
                      f"({state.skipped} skipped, {state.failed} failed)")
        else:
            if ctl.fit_preload is not None:  # its imports done (no two threads import one module)
                ctl.fit_preload.join()
            try:
                from calib.fit.progress import Progress

                wall0, cpu0 = time.monotonic(), time.thread_time()
                summary.fit, summary.result_path, summary.report_path = fit_run_log(
                    state.log_path, ctl.lp, progress=Progress(state.fitting, every_s=1.0))
                log.info("run %s: fitted in %.2f s (%.2f CPU-s in this thread)", state.run_id,
                         time.monotonic() - wall0, time.thread_time() - cpu0)
            except (ValueError, RuntimeError, ArithmeticError) as exc:
                reason = f"no result: the fit of {state.measured} measured configuration(s) failed: {exc}"
            if summary.fit is not None and summary.adaptive is not None:
                _add_adaptive(summary)
        if summary.fit is None:
            log.error("run %s: %s", state.run_id, reason)
            end = "failed"
    with state.lock:
        state.reason = reason if end == "failed" else state.reason
    state.set(end, reason)
    summary.state = end
    summary.reason = reason
    pub.release_bus()  # after the final state went out on the bus
    return summary


def _add_adaptive(summary) -> None:
    """An adaptive run's summary into ``result.json`` (``adaptive``): why it stopped, the predicted
    intervals against the number of configurations, the cell time saved against the full plan."""
    from calib.fit.result import write_result

    from acquire.run.adaptive import found_after_the_fact

    summary.adaptive["found"] = found_after_the_fact(summary.adaptive, summary.fit)
    summary.fit["adaptive"] = summary.adaptive
    if summary.result_path is not None:
        write_result(summary.result_path, summary.fit)
    if summary.report_path is not None:  # the report was written by the fit: add the section before its end
        from calib.report.report_adaptive import adaptive_section

        try:
            text = summary.report_path.read_text(encoding="utf-8")
            end = text.rfind("</body>")
            if end >= 0:
                section = "\n".join(adaptive_section(summary.adaptive)) + "\n"
                summary.report_path.write_text(text[:end] + section + text[end:], encoding="utf-8")
        except OSError as exc:
            log.warning("report: the adaptive run's section not added: %s", exc)
