"""What a run shows on the console and keeps in its text log (acquire/live/console.py)."""

from __future__ import annotations

import logging

import pytest

from acquire.live.console import RunLogFile, console_level, display_path


def test_display_path_is_normalised_and_relative_inside_the_working_folder(tmp_path):
    inside = tmp_path / "fixtures" / "plans" / ".." / ".." / "runs" / "r1" / "r1.mcap"
    assert display_path(inside, cwd=tmp_path) == "runs/r1/r1.mcap"
    outside = tmp_path / "a" / ".." / "b.mcap"
    assert display_path(outside, cwd=tmp_path / "elsewhere") == str(tmp_path / "b.mcap")
    assert display_path(None) == "-"


@pytest.mark.parametrize("verbose, tty, level", [
    (0, True, logging.WARNING), (1, True, logging.INFO), (2, True, logging.DEBUG),
    (0, False, logging.INFO), (2, False, logging.DEBUG),
])
def test_console_shows_warnings_on_a_terminal_info_with_v_and_off_a_terminal(verbose, tty, level):
    assert console_level(verbose, tty) == level


@pytest.fixture
def quiet_root():
    root = logging.getLogger()
    saved = (root.level, list(root.handlers))
    root.setLevel(logging.DEBUG)
    yield root
    root.setLevel(saved[0])
    root.handlers[:] = saved[1]


def test_run_log_file_writes_what_came_before_it_existed_then_everything(tmp_path, quiet_root):
    dev = logging.getLogger("remaster.device.test")
    logfile = RunLogFile(logging.INFO)
    dev.info("connecting to 127.0.0.1:30200")
    dev.debug("not kept at INFO")
    mcap = tmp_path / "r1" / "r1.mcap"
    mcap.parent.mkdir()
    assert logfile.open(mcap) == tmp_path / "r1" / "r1.log"
    dev.warning("late answer")
    logfile.close()
    dev.info("after the run: not in its log")
    lines = (tmp_path / "r1" / "r1.log").read_text().splitlines()
    assert [ln.split(" ", 2)[2] for ln in lines] == [
        "INFO remaster.device.test: connecting to 127.0.0.1:30200",
        "WARNING remaster.device.test: late answer",
    ]


def test_run_without_a_folder_prints_what_the_console_did_not_show(tmp_path, quiet_root, capsys):
    dev = logging.getLogger("remaster.device.test")
    logfile = RunLogFile(logging.INFO)
    dev.info("session IDLE -> MONITORING_WAIT")
    dev.error("connection refused")  # the console showed this one already
    logfile.close(shown_level=logging.WARNING)
    err = capsys.readouterr().err
    assert "the run made no log folder" in err
    assert "session IDLE -> MONITORING_WAIT" in err and "connection refused" not in err
    assert not list(tmp_path.iterdir())


def test_a_foreseen_run_failure_is_one_console_line_and_its_traceback_stays_in_the_text_log(tmp_path, quiet_root):
    """Seen: "3 configurations failed in a row" printed a Python traceback on the console. A
    failure the product foresees (a RunError, a DriverError) is one line there; the run's text
    log keeps the traceback for whoever debugs it."""
    import io

    from acquire.live.console import ConsoleFormatter, FORESEEN
    from acquire.run.summary import RunError

    console = io.StringIO()
    handler = logging.StreamHandler(console)
    handler.setFormatter(ConsoleFormatter("%(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.WARNING)
    quiet_root.addHandler(handler)
    logfile = RunLogFile(logging.INFO)
    mcap = tmp_path / "r1" / "r1.mcap"
    mcap.parent.mkdir()
    logfile.open(mcap)
    run_log = logging.getLogger("acquire.run")
    try:
        raise RunError("3 configurations failed in a row (last: move refused); the cell is not usable")
    except RunError as exc:
        run_log.error("run r1 failed: %s", exc, exc_info=exc, extra=FORESEEN)
    try:
        raise KeyError("a bug")
    except KeyError:
        run_log.exception("run r1 failed")  # not foreseen: the traceback on the console too
    logfile.close()
    shown = console.getvalue().splitlines()
    assert shown[0] == ("ERROR acquire.run: run r1 failed: 3 configurations failed in a row (last: move refused); "
                        "the cell is not usable")
    assert shown[1] == "ERROR acquire.run: run r1 failed" and "Traceback (most recent call last):" in shown[2]
    text = (tmp_path / "r1" / "r1.log").read_text()
    assert text.count("Traceback (most recent call last):") == 2 and "acquire.run.summary.RunError: 3 configurations" in text


def test_with_vv_the_console_shows_the_traceback_of_a_foreseen_failure_too():
    from acquire.live.console import ConsoleFormatter, FORESEEN

    try:
        raise ValueError("boom")
    except ValueError:
        import sys

        record = logging.LogRecord("acquire.run", logging.ERROR, __file__, 1, "run r1 failed: boom", None,
                                   sys.exc_info())
    record.__dict__.update(FORESEEN)
    assert ConsoleFormatter("%(message)s").format(record) == "run r1 failed: boom"
    assert "Traceback (most recent call last):" in ConsoleFormatter("%(message)s", tracebacks=True).format(record)
    assert record.exc_info is not None  # left for the text log's handler
