"""Robot target files (``calib.io.targets``): KUKA .dat E6POS, ABB RAPID robtargets, our CSV —
read with their configuration data, written back with only the pose changed, bad input named by
file, line and field."""

from __future__ import annotations

from pathlib import Path

import pytest

from calib.io.targets import TargetFileError, read_targets, write_patched

KRL = (
    "&ACCESS RVP\r\n&REL 3\r\nDEFDAT  weld\r\n;FOLD EXTERNAL DECLARATIONS\r\n;ENDFOLD\r\n"
    "DECL E6POS XP1={X 541.581,Y -115.587,Z 653.268,A 153.0034,B 33.7875,C -176.5481,S 6,T 34,E1 0.0,E2 0.0}\r\n"
    "DECL FDAT FP1={TOOL_NO 1,BASE_NO 0,IPO_FRAME #BASE,POINT2[] \" \"}\r\n"
    "DECL GLOBAL POS XP2={x 1.5E+02, y -2, z 300.25, a 0, b 90, c 0, s 2, t 10}\r\n"
    "DECL E6AXIS XHOME={A1 0.0,A2 -90.0,A3 90.0,A4 0.0,A5 0.0,A6 0.0}\r\n"
    "ENDDAT\r\n"
)
RAPID = """MODULE Welds
    ! taught 2026-11-30
    CONST robtarget p10:=[[500.1,-20,600],[0.707107,0,0.707107,0],[0,-1,2,1],[9E+09,9E+09,9E+09,9E+09,9E+09,9E+09]];
    PERS robtarget p20 := [ [ 400, 10.5, 350 ], [1, 0, 0, 0], [-1,0,-1,0], [9E+09,9E+09,9E+09,9E+09,9E+09,9E+09] ];
    PROC main()
        MoveL p10, v100, fine, tool0;
    ENDPROC
ENDMODULE
"""


def test_kuka_declarations_are_read_with_their_status_and_turn(tmp_path):
    path = tmp_path / "weld.dat"
    path.write_bytes(KRL.encode("latin-1"))
    tf = read_targets(path)
    assert tf.format == "kuka" and [t.name for t in tf.targets] == ["XP1", "XP2"]
    assert tf.targets[0].values == (541.581, -115.587, 653.268, 153.0034, 33.7875, -176.5481)
    assert tf.targets[0].config == {"S": 6, "T": 34} and tf.targets[0].line == 6
    assert tf.targets[1].values == (150.0, -2.0, 300.25, 0.0, 90.0, 0.0) and tf.targets[1].config == {"S": 2, "T": 10}


def test_kuka_file_written_back_changes_only_the_pose_numbers(tmp_path):
    path = tmp_path / "weld.dat"
    path.write_bytes(KRL.encode("latin-1"))
    tf = read_targets(path)
    out = tmp_path / "out.dat"
    write_patched(tf, {"XP1": (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)}, out)
    text = out.read_bytes().decode("latin-1")
    assert text == KRL.replace("X 541.581,Y -115.587,Z 653.268,A 153.0034,B 33.7875,C -176.5481",
                               "X 1.0000,Y 2.0000,Z 3.0000,A 4.00000,B 5.00000,C 6.00000")
    assert read_targets(out).targets[0].values == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)


def test_rapid_robtargets_are_read_and_only_position_and_orientation_change(tmp_path):
    path = tmp_path / "Welds.mod"
    path.write_text(RAPID)
    tf = read_targets(path)
    assert tf.format == "rapid" and [t.name for t in tf.targets] == ["p10", "p20"]
    p10 = tf.targets[0]
    assert p10.values[:3] == (500.1, -20.0, 600.0) and p10.config == {"cf": [0, -1, 2, 1]} and p10.line == 3
    assert p10.values[3:] == pytest.approx((0.7071068, 0, 0.7071068, 0), abs=1e-6)  # normalised, w first
    out = tmp_path / "out.mod"
    write_patched(tf, {"p20": (1.5, 2.5, 3.5, 0.0, 1.0, 0.0, 0.0)}, out)
    assert out.read_text() == RAPID.replace("[ [ 400, 10.5, 350 ], [1, 0, 0, 0],",
                                            "[ [ 1.5000, 2.5000, 3.5000 ], [0.000000000, 1.000000000, 0.000000000, 0.000000000],")


@pytest.mark.parametrize("name,text,message", [
    ("a.dat", "DECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0,S 2,T 0}\n", r"a\.dat:1: XP1: no C"),
    ("a.dat", "DEFDAT a\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0,C 0,S 2.5,T 0}\n", r"a\.dat:2: XP1: field S is 2.5; allowed: a whole number"),
    ("a.dat", "DEFDAT a\nENDDAT\n", "no DECL E6POS/POS declarations found"),
    ("a.mod", "CONST robtarget p:=[[1,2],[1,0,0,0],[0,0,0,0],[9E9]];\n", r"a\.mod:1: p: trans \[x,y,z\] has 2 numbers; allowed: 3"),
    ("a.mod", "\n\nCONST robtarget p:=[[1,2,3],[0.5,0,0,0],[0,0,0,0],[9E9]];\n", r"a\.mod:3: p: the quaternion's norm is 0.500000"),
    ("a.csv", "name,x,y,z,a,b\n", r"a\.csv:1: header lacks c"),
    ("a.csv", "name,x,y,z,a,b,c\np1,1,2,three,0,0,0\n", r"a\.csv:2: p1: field z is 'three', not a number"),
    ("a.txt", "x", r"cannot tell the format from the suffix '\.txt'"),
])
def test_bad_files_are_refused_naming_file_line_and_field(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(TargetFileError, match=message):
        read_targets(path)


def test_csv_targets_carry_their_configuration_columns(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("# cell 3\nname,x,y,z,a,b,c,q1,q2,q3,q4,q5,q6\np1,500,0,600,0,90,0,0,-90,90,0,45,0\n")
    t = read_targets(path).targets[0]
    assert t.values == (500, 0, 600, 0, 90, 0) and t.config["joints_deg"] == [0, -90, 90, 0, 45, 0] and t.line == 3


def test_declarations_the_reader_does_not_take_are_refused_not_left_behind(tmp_path):
    path = tmp_path / "a.mod"
    path.write_text("MODULE a\n  CONST robtarget p1:=[[1,2,3],[1,0,0,0],[0,0,0,0],[9E9,9E9,9E9,9E9,9E9,9E9]];\n"
                    "  CONST robtarget path{2}:=[[[1,2,3],[1,0,0,0],[0,0,0,0],[9E9]],[[4,5,6],[1,0,0,0],[0,0,0,0],[9E9]]];\n"
                    "ENDMODULE\n")
    with pytest.raises(TargetFileError, match=r"a\.mod:3: a robtarget declaration this reader does not understand"):
        read_targets(path)
    multi = tmp_path / "b.mod"
    multi.write_text("CONST robtarget p1:=[[1,2,3],\n    [1,0,0,0],\n    [0,0,0,0],[9E9]];\n")
    assert read_targets(multi).targets[0].values[:3] == (1, 2, 3)
    dat = tmp_path / "a.dat"
    dat.write_text("DEFDAT a\nDECL E6POS XP1={X 1,Y 2,Z 3,A 0,B 0,C 0}\nDECL E6POS XP2=XP1\nENDDAT\n")
    with pytest.raises(TargetFileError, match=r"a\.dat:3: an E6POS/POS declaration this reader does not understand"):
        read_targets(dat)
