"""Where a recording goes: never over an existing one by accident, a new file per start with {start}."""

from datetime import UTC, datetime

import pytest

from rig.recorder import RecordingExists, check_recording_path, open_recording

START = datetime(2026, 11, 23, 3, 15, 0, 400_000, tzinfo=UTC)
MCAP_MAGIC = b"\x89MCAP0\r\n"


def test_start_in_the_name_is_the_utc_start_second(tmp_path):
    with open_recording(tmp_path / "rig-{start}.mcap", start_utc=START) as log:
        assert log.path == tmp_path / "rig-20261123T031500Z.mcap"
    assert log.path.read_bytes().startswith(MCAP_MAGIC)


def test_starts_within_one_second_get_files_of_their_own(tmp_path):
    # A restart loop, or a board without a clock that repeats its boot time before it syncs: the
    # rig must still start and lose nothing, so the second start takes the next free name.
    first = tmp_path / "rig-20261123T031500Z.mcap"
    first.write_bytes(b"the first start's drive")
    names = []
    for _ in range(2):
        with open_recording(tmp_path / "rig-{start}.mcap", start_utc=START) as log:
            names.append(log.path.name)
    assert names == ["rig-20261123T031500Z-1.mcap", "rig-20261123T031500Z-2.mcap"]
    assert first.read_bytes() == b"the first start's drive"


def test_an_existing_file_is_refused_and_kept(tmp_path):
    keep = tmp_path / "drive.mcap"
    keep.write_bytes(b"yesterday's drive")
    with pytest.raises(RecordingExists) as err:
        check_recording_path(keep)
    assert err.value.path == keep and not err.value.folder
    # Made between the check and the open (a camera can take 15 s to start): still not truncated.
    with pytest.raises(RecordingExists):
        open_recording(keep, start_utc=START)
    assert keep.read_bytes() == b"yesterday's drive"


def test_overwrite_replaces_an_existing_file(tmp_path):
    old = tmp_path / "drive.mcap"
    old.write_bytes(b"yesterday's drive")
    check_recording_path(old, overwrite=True)
    with open_recording(old, start_utc=START, overwrite=True) as log:
        assert log.path == old
    assert old.read_bytes().startswith(MCAP_MAGIC)


def test_a_folder_is_refused_even_with_overwrite(tmp_path):
    for overwrite in (False, True):
        with pytest.raises(RecordingExists) as err:
            check_recording_path(tmp_path, overwrite=overwrite)
        assert err.value.folder
        with pytest.raises(RecordingExists):
            open_recording(tmp_path, start_utc=START, overwrite=overwrite)


def test_a_name_with_start_is_checked_when_the_file_is_made(tmp_path):
    (tmp_path / "rig-20261123T031500Z.mcap").write_bytes(b"x")
    check_recording_path(tmp_path / "rig-{start}.mcap")  # any start may be free: nothing to refuse yet
    assert not (tmp_path / "rig-{start}.mcap").exists()
