"""The station's archive: stored by serial and date, checksums verified, resumable, idempotent."""

import hashlib
import json
import shutil

import pytest

from acquire.station.archive import Archive, ArchiveError, ArchiveFull, ArchiveRefused, Limits, RunRef


def _files(contents: dict[str, bytes]) -> list[dict]:
    return [{"name": n, "bytes": len(b), "sha256": hashlib.sha256(b).hexdigest()} for n, b in contents.items()]


CONTENT = {"r1.mcap": bytes(range(256)) * 40, "result.json": b'{"format": "remaster.fit/1"}', "report.html": b"<html/>"}
REF = RunRef("plant-a", "c1", "r1", "KR6-0815")


def _send(transfer, contents, chunk=1000):
    for name, data in contents.items():
        off = transfer.offset(name)
        while off < len(data):
            off = transfer.write(name, off, data[off:off + chunk])


def test_a_run_is_stored_by_serial_and_date_with_a_verified_manifest(tmp_path):
    archive = Archive(tmp_path)
    t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    _send(t, CONTENT)
    manifest = t.finish()
    folder = tmp_path / "KR6-0815" / "2026-11-26" / "r1"
    assert archive.folder(manifest) == folder
    assert (folder / "r1.mcap").read_bytes() == CONTENT["r1.mcap"]
    assert json.loads((folder / "manifest.json").read_text())["files"] == sorted(_files(CONTENT), key=lambda f: f["name"])
    assert archive.verify(manifest) == []
    (folder / "report.html").write_bytes(b"<html>tampered")
    assert archive.verify(manifest) == [f"{folder / 'report.html'}: 14 bytes, the manifest says 7"]


def test_an_interrupted_transfer_resumes_at_its_offset_without_loss_or_duplicate(tmp_path):
    archive = Archive(tmp_path)
    t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    t.write("r1.mcap", 0, CONTENT["r1.mcap"][:3000])
    # The station restarts: a new Archive and Transfer find the partial file.
    t2 = Archive(tmp_path).begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    assert t2.offset("r1.mcap") == 3000
    with pytest.raises(ArchiveError, match="resume at 3000"):
        t2.write("r1.mcap", 0, CONTENT["r1.mcap"][:1000])  # a duplicate chunk is refused
    _send(t2, CONTENT)
    manifest = t2.finish()
    assert (archive.folder(manifest) / "r1.mcap").read_bytes() == CONTENT["r1.mcap"]
    assert len(archive.manifests()) == 1


def test_a_corrupted_file_is_refused_and_fetched_again(tmp_path):
    archive = Archive(tmp_path)
    files = _files(CONTENT)
    t = archive.begin(REF, files, "2026-11-26T10:00:00+00:00")
    bad = dict(CONTENT, **{"result.json": b'{"format": "remaster.fit/X"}'})
    _send(t, bad)
    with pytest.raises(ArchiveError, match="result.json: sha256 .* does not match"):
        t.finish()
    assert archive.manifest(REF) is None
    assert t.missing() == {"result.json": 0}
    _send(t, CONTENT)
    assert t.finish()["run_id"] == "r1"


def test_a_re_sent_run_is_not_stored_twice(tmp_path):
    archive = Archive(tmp_path)
    for _ in range(2):
        t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
        _send(t, CONTENT)
        t.finish()
    assert archive.is_complete(REF, _files(CONTENT))
    assert len(archive.manifests()) == 1
    assert sorted(p.name for p in (tmp_path / "KR6-0815" / "2026-11-26").iterdir()) == ["r1"]


def test_names_that_could_leave_the_archive_are_refused(tmp_path):
    archive = Archive(tmp_path)
    with pytest.raises(ArchiveError, match=r"files\[0\].name '../x' is not allowed"):
        archive.begin(REF, [{"name": "../x", "bytes": 1, "sha256": "0" * 64}], "2026-11-26T10:00:00+00:00")
    with pytest.raises(ArchiveError, match="robot_serial"):
        RunRef("", "c1", "r1", "../../etc")


def test_a_run_that_changed_after_it_was_archived_is_kept_beside_the_first_copy(tmp_path):
    archive = Archive(tmp_path)
    t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    _send(t, CONTENT)
    first = t.finish()
    grown = dict(CONTENT, **{"r1.resume1.mcap": b"more samples"})
    t = archive.begin(REF, _files(grown), "2026-11-27T09:00:00+00:00")
    _send(t, grown)
    second = t.finish()
    assert second["version"] == 2 and archive.folder(second).name == "r1.v2"
    assert archive.verify(first) == [] and archive.verify(second) == []
    assert archive.manifest(REF)["version"] == 2


def test_a_folder_holding_another_run_is_never_replaced(tmp_path, caplog):
    """A cell files a run whose folder (serial/day/run-id) already holds another cell's run: refused,
    logged, the stored run byte for byte as it was (before: rmtree of the existing folder)."""
    archive = Archive(tmp_path)
    t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    _send(t, CONTENT)
    first = t.finish()
    folder = archive.folder(first)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    other = RunRef("plant-a", "c2", "r1", "KR6-0815")   # same serial, day and run id, another cell
    evil = {"r1.mcap": b"not the robot's log", "result.json": b'{"joint_offsets": []}'}
    with pytest.raises(ArchiveRefused, match="never replaced"):   # refused when announced: no byte fetched
        archive.begin(other, _files(evil), "2026-11-26T11:00:00+00:00")
    # A folder taken between announcement and commit (another transfer won the race): refused at commit.
    shutil.move(folder, tmp_path / "aside")
    t = archive.begin(other, _files(evil), "2026-11-26T11:00:00+00:00")
    _send(t, evil)
    shutil.move(tmp_path / "aside", folder)
    with pytest.raises(ArchiveRefused, match="never replaced"):
        t.finish()
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert archive.verify(first) == [] and archive.manifest(other) is None
    assert "never replaced" in caplog.text
    assert archive.expected_bytes() == 0   # the refused transfer no longer counts


def test_a_one_tebibyte_announcement_is_refused_before_any_byte(tmp_path):
    archive = Archive(tmp_path, Limits(max_file_bytes=1 << 30, max_run_bytes=2 << 30, reserve_free_bytes=0))
    huge = [{"name": "r1.mcap", "bytes": 1 << 40, "sha256": "0" * 64}]
    with pytest.raises(ArchiveFull, match="over limits.max_file_bytes .* before any byte"):
        archive.begin(REF, huge, "2026-11-26T10:00:00+00:00")
    many = [{"name": f"r1.{i}.mcap", "bytes": 1 << 29, "sha256": "0" * 64} for i in range(5)]
    with pytest.raises(ArchiveFull, match="over limits.max_run_bytes"):
        archive.begin(REF, many, "2026-11-26T10:00:00+00:00")
    assert not any((tmp_path / ".incoming").iterdir())   # nothing was opened


def test_the_free_space_reserve_is_kept_when_announced_and_while_streaming(tmp_path):
    archive = Archive(tmp_path, Limits(reserve_free_bytes=0))
    free = archive.free_bytes()
    big = [{"name": "r1.mcap", "bytes": free + (1 << 30), "sha256": "0" * 64}]
    with pytest.raises(ArchiveFull, match="reserve_free_bytes"):
        Archive(tmp_path, Limits(max_file_bytes=1 << 62, max_run_bytes=1 << 62, reserve_free_bytes=0)).begin(
            REF, big, "2026-11-26T10:00:00+00:00")
    # Announced within the reserve, then the disk fills up (the reserve grows under it): the next chunk is refused.
    archive = Archive(tmp_path, Limits(reserve_free_bytes=0))
    t = archive.begin(REF, _files(CONTENT), "2026-11-26T10:00:00+00:00")
    t.write("r1.mcap", 0, CONTENT["r1.mcap"][:1000])
    archive.limits = Limits(reserve_free_bytes=archive.free_bytes())
    with pytest.raises(ArchiveFull, match="reserve_free_bytes"):
        t.write("r1.mcap", 1000, CONTENT["r1.mcap"][1000:2000])
    assert t.offset("r1.mcap") == 1000


def test_a_run_whose_result_is_not_a_fit_is_archived_without_a_history_entry(tmp_path, caplog):
    from acquire.station.history import load_history
    from acquire.station.intake import record_run

    archive = Archive(tmp_path)
    bad = {"r1.mcap": b"log", "result.json": b"{not json"}
    t = archive.begin(REF, _files(bad), "2026-11-26T10:00:00+00:00")
    _send(t, bad)
    manifest = t.finish()
    assert record_run(archive, manifest) is None
    assert load_history(tmp_path, "KR6-0815") == [] and archive.verify(manifest) == []
    assert "is not a result the history can use" in caplog.text


def test_a_run_stored_but_not_recorded_is_added_to_its_history_at_start(tmp_path):
    """A station killed between storing a run and recording it: the cell has its confirmation and
    never sends it again, so the next start adds it from the archive (once)."""
    from acquire.station.history import load_history
    from acquire.station.intake import catch_up

    archive = Archive(tmp_path)
    result = {"format": "remaster.fit/1", "data": {"n_configurations": 20},
              "joint_offsets": [{"joint": "A1", "value_deg": 0.1, "std_deg": 0.01, "identifiable": True}]}
    run = {"r1.mcap": b"log", "result.json": json.dumps(result).encode()}
    t = archive.begin(REF, _files(run), "2026-11-26T10:00:00+00:00")
    _send(t, run)
    t.finish()   # … and the station dies before record_run
    plain = RunRef("plant-a", "c1", "r2", "KR6-0815")
    t = archive.begin(plain, _files({"r2.mcap": b"log"}), "2026-11-27T10:00:00+00:00")
    _send(t, {"r2.mcap": b"log"})
    t.finish()   # a run without a result has no history entry to catch up
    assert load_history(tmp_path, "KR6-0815") == []
    assert catch_up(archive) == ["r1"]
    assert [e["run_id"] for e in load_history(tmp_path, "KR6-0815")] == ["r1"]
    assert catch_up(archive) == []
