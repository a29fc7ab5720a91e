"""Spreadsheet CSV exports for `acquire fit`: `;` and tab separators, decimal commas, a BOM —
read as meant, or refused with a message that names the separator or decimal mark."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.measure.dataset import DatasetError, read_csv
from calib.robot.model import load_robot_model
from calib.fit.socket import SocketDataError, read_socket_csv

# One xdist worker runs this file: its module fixture (the reference fit) is computed once, not once per worker.
pytestmark = pytest.mark.xdist_group("calib/test_csv_dialects")

ROOT = Path(__file__).resolve().parents[2]
IIWA = load_robot_model(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml")
CAL = ROOT / "fixtures" / "datasets" / "iiwa14_sim_cal.csv"


def spreadsheet(text: str, sep: str = ";", decimal: str = ",") -> str:
    """``text`` (comma-separated, decimal points) as a spreadsheet in another locale saves it."""
    out = []
    for line in text.splitlines():
        if line.startswith("#"):
            out.append(line)
            continue
        cells = line.split(",")
        out.append(sep.join(c.replace(".", decimal) if re.fullmatch(r"[-+0-9.eE]+", c) else c for c in cells))
    return "\n".join(out) + "\n"


@pytest.fixture(scope="module")
def reference():
    return read_csv(CAL, IIWA)


def assert_same(ds, ref):
    np.testing.assert_array_equal(ds.q_rad, ref.q_rad)
    np.testing.assert_array_equal(ds.xyz_mm, ref.xyz_mm)
    np.testing.assert_array_equal(ds.std_mm, ref.std_mm)
    for f in ("config", "pose", "marker", "sensor", "count", "split"):
        np.testing.assert_array_equal(getattr(ds, f), getattr(ref, f))


@pytest.mark.parametrize(
    "sep, decimal, bom",
    [(";", ",", False), (";", ".", False), ("\t", ",", False), ("\t", ".", False), (";", ",", True), (",", ".", True)],
    ids=["semicolon-decimal-comma", "semicolon-decimal-point", "tab-decimal-comma", "tab", "excel-bom", "bom"],
)
def test_spreadsheet_exports_read_the_same_numbers(tmp_path, reference, sep, decimal, bom):
    text = spreadsheet(CAL.read_text(), sep, decimal)
    path = tmp_path / "export.csv"
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.replace("\n", "\r\n").encode())
    assert_same(read_csv(path, IIWA), reference)


def test_quoted_decimal_commas_in_a_comma_separated_file_are_read(tmp_path, reference):
    lines = CAL.read_text().splitlines()
    out = []
    for line in lines:
        if line.startswith("#") or line.startswith("config"):
            out.append(line)
        else:
            out.append(",".join(f'"{c.replace(".", ",")}"' if re.fullmatch(r"[-+0-9.eE]+", c) else c
                                for c in line.split(",")))
    path = tmp_path / "quoted.csv"
    path.write_text("\n".join(out) + "\n")
    assert_same(read_csv(path, IIWA), reference)


def test_thousands_points_with_decimal_commas_are_read(tmp_path):
    text = ("config;pose;q1;q2;q3;q4;q5;q6;q7;x;y;z\n"
            "c1;p1;0;30;0;-60;0;45;0;1.523,112;-212,604;431,877\n")
    path = tmp_path / "grouped.csv"
    path.write_text(text)
    ds = read_csv(path, IIWA)
    np.testing.assert_array_equal(ds.xyz_mm[0], [1523.112, -212.604, 431.877])


def test_unquoted_decimal_commas_in_a_comma_separated_file_are_refused_by_name(tmp_path):
    text = CAL.read_text().splitlines()
    head = [l for l in text if not l.startswith("#")][0]
    row = [l for l in text if not l.startswith("#")][1].replace(".", ",")
    path = tmp_path / "ambiguous.csv"
    path.write_text(head + "\n" + row + "\n")
    with pytest.raises(DatasetError) as info:
        read_csv(path, IIWA)
    msg = str(info.value)
    assert f"{path}:2:" in msg and "decimal commas in a comma-separated file" in msg
    assert "export with ';' as the separator or '.' as the decimal mark" in msg


def test_mixed_decimal_marks_are_refused_naming_a_line_of_each(tmp_path):
    text = ("config;pose;q1;q2;q3;q4;q5;q6;q7;x;y;z\n"
            "c1;p1;0;30;0;-60;0;45;0;1523,1;-212,6;431,8\n"
            "c2;p1;0;30;0;-60;0;45;0;1523.1;-212.6;431.8\n")
    path = tmp_path / "mixed.csv"
    path.write_text(text)
    with pytest.raises(DatasetError, match=r"mixed decimal marks: line 2 has a decimal comma \('1523,1'\), "
                                           r"line 3 a decimal point \('1523.1'\)"):
        read_csv(path, IIWA)


def test_a_header_mixing_separators_is_refused_naming_both(tmp_path):
    path = tmp_path / "mixed_sep.csv"
    path.write_text("config;pose,q1;q2;q3;q4;q5;q6;q7;x;y;z\n")
    with pytest.raises(DatasetError, match=r"mixed_sep.csv:1: the header mixes separators \(comma ',' and "
                                           r"semicolon ';'"):
        read_csv(path, IIWA)


def test_an_unknown_separator_is_refused_without_the_old_zero_joint_columns_message(tmp_path):
    path = tmp_path / "pipes.csv"
    path.write_text("config|pose|q1|q2|q3|q4|q5|q6|q7|x|y|z\nc1|p1|0|30|0|-60|0|45|0|1|2|3\n")
    with pytest.raises(DatasetError) as info:
        read_csv(path, IIWA)
    assert "the header is one column" in str(info.value) and "commas, semicolons or tabs" in str(info.value)
    assert "0 joint columns" not in str(info.value)


def test_a_file_in_another_encoding_is_refused_saying_how_to_save_it(tmp_path):
    path = tmp_path / "latin1.csv"
    path.write_bytes(("# Kalibrierung Zelle 3, Prüfer: Jürgen\n" + spreadsheet(CAL.read_text())).encode("latin-1"))
    with pytest.raises(DatasetError, match="not UTF-8 text.*CSV UTF-8"):
        read_csv(path, IIWA)


def test_acquire_fit_reads_a_semicolon_decimal_comma_export(tmp_path):
    from acquire.cli import app

    path = tmp_path / "export.csv"
    path.write_text(spreadsheet(CAL.read_text()))
    result = CliRunner().invoke(app, ["fit", str(path), "--robot", str(ROOT / "fixtures" / "robots" / "kuka_iiwa14_r820.yaml"),
                                      "-o", str(tmp_path / "result.json"), "--link-tolerance", "none"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "result.json").is_file()


# --- socket data -------------------------------------------------------------------------------
SOCKET_ROWS = np.array([[-12.12, 67.64, 14.78, -85.78, -28.06, 37.62, 0.31],
                        [10.5, 60.25, -3.5, -80.125, 20.0, 45.75, -15.0],
                        [30.0, 55.5, 12.0, -70.25, -10.5, 50.0, 30.0],
                        [-25.75, 70.0, 5.5, -90.0, 15.25, 30.5, -45.0],
                        [5.0, 65.0, -8.0, -75.5, 0.5, 40.0, 60.0],
                        [-5.0, 62.5, 2.0, -82.0, -5.0, 35.0, -60.0]])


def socket_text(sep: str, decimal: str, distance: str = "50") -> str:
    lines = [f"# socket_distance_mm: {distance}", sep.join(["config", *[f"q{i}" for i in range(1, 8)], "placement", "socket"])]
    for i, q in enumerate(SOCKET_ROWS):
        cells = [f"{v:g}".replace(".", decimal) for v in q]
        lines.append(sep.join([f"c{i:03d}", *cells, "front", str(i % 2)]))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("sep, decimal, distance", [(",", ".", "50"), (";", ",", "50,02"), ("\t", ",", "50,02"),
                                                    (";", ".", "50.02")])
def test_socket_files_in_spreadsheet_dialects_read_the_same_angles(tmp_path, sep, decimal, distance):
    path = tmp_path / "sockets.csv"
    path.write_text(socket_text(sep, decimal, distance))
    ds = read_socket_csv(path, 7)
    np.testing.assert_array_equal(ds.q_rad, np.radians(SOCKET_ROWS))
    assert ds.groups == [("front", "0"), ("front", "1")]
    assert ds.distances[0][2] == float(distance.replace(",", "."))


def test_socket_files_are_recognised_by_acquire_fit_in_any_dialect(tmp_path):
    from calib.io.csvdialect import is_socket_csv

    for i, sep in enumerate([",", ";", "\t"]):
        path = tmp_path / f"s{i}.csv"
        path.write_text(socket_text(sep, "," if sep != "," else "."))
        assert is_socket_csv(path), sep


def test_socket_files_with_mixed_decimal_marks_are_refused(tmp_path):
    text = socket_text(";", ",").splitlines()
    text[3] = text[3].replace(",", ".")
    path = tmp_path / "mixed.csv"
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(SocketDataError, match=r"mixed decimal marks: line 3 has a decimal comma .* line 4 a decimal point"):
        read_socket_csv(path, 7)


@pytest.mark.parametrize("column", ["x", "qw"])
def test_a_header_naming_a_column_twice_is_refused_with_file_line_and_columns(tmp_path, column):
    """A spreadsheet column pasted twice (``x``, or an orientation column) was fitted silently with
    the last one: which value is meant cannot be known, so nothing is read."""
    lines = [ln for ln in CAL.read_text().splitlines()]
    head = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    header = lines[head].split(",")
    extra = [column] if column in header else ["qw", "qx", "qy", "qz", column]
    lines[head] = ",".join(header + extra)
    for i in range(head + 1, len(lines)):
        if lines[i] and not lines[i].startswith("#"):
            lines[i] = ",".join(lines[i].split(",") + ["1.0" if c == "qw" else "0.0" for c in extra])
    path = tmp_path / "twice.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        read_csv(path, IIWA)
    text = str(info.value)
    assert text.startswith(f"{path}:{head + 1}: the header names a column more than once")
    first = header.index(column) + 1 if column in header else len(header) + 1
    assert f"'{column}' in columns {first}, {len(header) + len(extra)}" in text
