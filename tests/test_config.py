"""Configuration: TOML covers every option, flags override, mistakes are named."""

import argparse
import inspect
import json
import math
import tomllib

import pytest

from rig.config import (
    DEFAULTS,
    ConfigError,
    check_option,
    check_window_fits,
    dump_toml,
    load_config,
    merge,
    override,
)


def _same(a, b):
    """Equal, with nan (TOML's "unset" for an optional number) equal to itself."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_defaults_round_trip_through_toml(tmp_path):
    text = dump_toml(load_config())
    assert _same(tomllib.loads(text), DEFAULTS)
    path = tmp_path / "rig.toml"
    path.write_text(text)
    assert _same(load_config(path), DEFAULTS)


def test_strings_with_quotes_backslashes_and_control_characters_round_trip():
    cfg = load_config()
    cfg["output"]["jsonl"] = 'C:\\logs\\"sun"\n\tnight é\x7f.jsonl'
    assert tomllib.loads(dump_toml(cfg))["output"]["jsonl"] == cfg["output"]["jsonl"]


def test_every_run_flag_has_a_config_option():
    from rig.cli import build_parser

    parser = build_parser()
    run = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["run"]
    cli_only = {"help", "debug", "config", "quiet", "fast", "record_frames", "source_baud"}
    dests = {a.dest for a in run._actions} - cli_only
    known = {key for section in DEFAULTS.values() for key in section}
    assert dests <= known | {"camera", "heading"}, sorted(dests - known)


def test_file_then_flags(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text('[output]\nserial = "/dev/ttyUSB0"\nbaud = 9600\n[window]\nspan_s = 6\n')
    cfg = load_config(path)
    assert cfg["output"]["serial"] == "/dev/ttyUSB0" and cfg["output"]["baud"] == 9600
    assert cfg["window"]["span_s"] == 6.0 and isinstance(cfg["window"]["span_s"], float)
    cfg = override(cfg, {"output.baud": 115200, "output.serial": None, "output.format": "binary"})
    assert cfg["output"]["baud"] == 115200  # the flag wins
    assert cfg["output"]["serial"] == "/dev/ttyUSB0"  # a flag not given changes nothing
    assert cfg["output"]["format"] == "binary"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[outptu]\nserial = 'x'\n", "unknown section [outptu]"),
        ("camera = 'oak'\n", "camera is outside any section; put it under [source]"),
        ("baud = 9600\n", "baud is outside any section; put it under [source] or [output]"),
        ("[output]\nbaudrate = 9600\n", "unknown option [output] baudrate; known: serial, baud"),
        ("[output]\nbaud = '9600'\n", "[output] baud: expected int, got '9600'"),
        ("[output]\nformat = 'xml'\n", "[output] format: expected one of nmea, binary"),
        ("[rig]\nrealtime = 1\n", "[rig] realtime: expected bool, got 1"),
        # TOML booleans are not numbers: `span_s = true` would otherwise become a 1 s window and
        # `baud = true` a 1 baud port, without a word.
        ("[window]\nspan_s = true\n", "[window] span_s: expected float, got True"),
        ("[output]\nbaud = true\n", "[output] baud: expected int, got True"),
        # A section written as a value (`output = "x"`) is named, not an AttributeError.
        ("output = 'x'\n", "[output] must be a table of options"),
        ("[output\n", "not valid TOML"),
        # Out of range: refused where the value is read, so `config --print` never shows a
        # configuration that `run` then refuses after opening a camera.
        ("[window]\nspan_s = -4\n", "[window] span_s: expected a finite number > 0, got -4.0"),
        ("[window]\nyaw_scale_deg = 0\n", "[window] yaw_scale_deg: expected a finite number in (0, 180]"),
        ("[rig]\nqueue_size = 0\n", "[rig] queue_size: expected an integer > 0, got 0"),
        # math.isfinite() overflowed on it: an internal error, not this line.
        (f"[rig]\nqueue_size = {'9' * 400}\n",
         "[rig] queue_size: expected an integer in (0, 2147483647], got 99999999999999999999... (400 characters)"),
        # The same for an option that takes a float: float() overflowed on it (an internal error).
        (f"[window]\nspan_s = {'9' * 400}\n",
         "[window] span_s: expected a finite number > 0, got 99999999999999999999... (400 characters)"),
        (f"[source]\ndeclination_deg = -{'9' * 400}\n",
         "[source] declination_deg: expected a finite number in [-180, 180], got -9999999999999999999... (401 "),
        # A long value of the wrong type or choice is cut too: the error stays one short line.
        (f"[rig]\nqueue_size = '{'x' * 5000}'\n",
         "[rig] queue_size: expected int, got 'xxxxxxxxxxxxxxxxxxx... (5002 characters)"),
        (f"[output]\nformat = '{'x' * 5000}'\n",
         "[output] format: expected one of nmea, binary, got 'xxxxxxxxxxxxxxxxxxx... (5002 characters)"),
        ("[source]\nmax_gap_s = nan\n", "[source] max_gap_s: expected a finite number > 0, got nan"),
        ("[source]\nhfov_deg = -1.0\n", "[source] hfov_deg: expected a finite number in [0, 179]"),
        ("[source]\ndeclination_deg = inf\n", "[source] declination_deg: expected a finite number in [-180, 180]"),
        ("[rig]\nring_max_age_s = inf\n", "[rig] ring_max_age_s: expected a finite number > 0, got inf"),
        ("[source]\nhfov_deg = 179.5\n", "[source] hfov_deg: expected a finite number in [0, 179], got 179.5"),
        # Narrower than any camera: fx of 1e302 px, whose crops overflowed (numpy warnings, or round(inf)).
        ("[source]\nhfov_deg = 1e-300\n",
         "[source] hfov_deg: expected 0 (unset) or at least 0.0001 deg, as any camera has, got 1e-300"),
        # A top-level value that is no option of any section is an unknown section, not misplaced.
        ("bogus = 1\n", "unknown section [bogus]"),
        ("camera = 'oak'\n", "camera is outside any section; put it under [source]"),
    ],
)
def test_mistakes_are_named(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert message in str(info.value)
    assert str(path) in str(info.value)  # which file: a rig may read several


def test_missing_file():
    with pytest.raises(ConfigError, match="does not exist"):
        load_config("/nonexistent/rig.toml")


def test_a_folder_or_non_utf8_file_is_named_with_what_to_do(tmp_path):
    # They were "[Errno 21] Is a directory" and a codec's message, with no way out.
    with pytest.raises(ConfigError, match=r"is a folder; pass the .toml file in it$"):
        load_config(tmp_path)
    latin = tmp_path / "rig.toml"
    latin.write_bytes("[source]\ncamera = 'caméra'\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"is not UTF-8 text \(line 2, column 14: byte 0xe9\); save it as UTF-8"):
        load_config(latin)


def test_a_file_that_never_ends_is_refused_without_reading_it_all(tmp_path):
    # --config /dev/zero grew by gigabytes until the machine killed the command.
    from rig.config import MAX_CONFIG_BYTES

    with pytest.raises(ConfigError, match=r"/dev/zero is over 1 MiB, which no config is; pass the --config"):
        load_config("/dev/zero")
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * MAX_CONFIG_BYTES + "\n")
    with pytest.raises(ConfigError, match="is over 1 MiB"):
        load_config(big)
    (tmp_path / "rig.toml").write_text("[window]\nspan_s = 5.0\n")
    assert load_config(tmp_path / "rig.toml")["window"]["span_s"] == 5.0


def test_defaults_are_those_of_what_they_configure():
    # `sunrig run` builds RigConfig, the pairing and the window from this table, so a default
    # changed in one place but not the other would make the CLI and the library disagree. The
    # expected values are the library's own defaults, read from it.
    from drivers.pairing import DEFAULT_MAX_AGE_S, DEFAULT_MAX_GAP_S
    from rig.pipeline import RigConfig
    from rig.window import SpreadWindowPolicy

    rig, lib = DEFAULTS["rig"], RigConfig()
    assert (rig["queue_size"], rig["ring_capacity"], rig["ring_max_age_s"], rig["status_every_s"],
            rig["max_latency_s"], rig["max_covered_share"]) == (
        lib.queue_size, lib.ring_capacity, lib.ring_max_age_s, lib.status_every_s, lib.max_latency_s,
        lib.exposure_gate.max_covered_share)
    assert DEFAULTS["source"]["max_gap_s"] == DEFAULT_MAX_GAP_S
    assert DEFAULTS["source"]["max_age_s"] == DEFAULT_MAX_AGE_S
    window = SpreadWindowPolicy()
    assert DEFAULTS["window"]["span_s"] == window.span_s
    assert DEFAULTS["window"]["yaw_scale_deg"] == pytest.approx(math.degrees(window.yaw_scale_rad))

    from drivers.gnss import DEFAULT_BAUD
    from drivers.pairing import HeadingInterpolator
    from estimator.estimator import SunEstimator
    from rig.publishers import SerialPublisher
    from rig.recorder import RecorderPublisher

    def default(fn, name):
        return inspect.signature(fn).parameters[name].default

    assert DEFAULTS["source"]["baud"] == DEFAULT_BAUD
    assert DEFAULTS["source"]["heading_latency_s"] == default(HeadingInterpolator, "latency_s")
    assert DEFAULTS["estimator"]["seed"] == default(SunEstimator, "seed")
    assert DEFAULTS["output"]["baud"] == default(SerialPublisher, "baudrate")
    assert DEFAULTS["output"]["record_frames"] == default(RecorderPublisher, "record_frames")


def test_an_existing_recording_is_refused_by_default():
    # A drive cannot be recorded again (rig/recorder.py): replacing a recording must be asked for.
    assert DEFAULTS["output"]["record_overwrite"] is False


def test_unset_values_and_every_default_are_in_range(tmp_path):
    # 0 means "unset" for the camera's own size, rate and field of view, and nan for the
    # declination (TOML has no null): those must pass, as must every default.
    path = tmp_path / "unset.toml"
    path.write_text("[source]\nhfov_deg = 0.0\nwidth = 0\nfps = 0.0\ndeclination_deg = nan\n")
    cfg = load_config(path)
    assert math.isnan(cfg["source"]["declination_deg"]) and cfg["source"]["width"] == 0
    assert math.isnan(check_option("source", "declination_deg", None))  # a flag left unset
    path.write_text("[source]\nhfov_deg = 179.0\ndeclination_deg = -180.0\n")  # the ends of closed ranges
    assert load_config(path)["source"]["hfov_deg"] == 179.0
    merge(load_config(), DEFAULTS, where="defaults")  # every default through the same checks


def test_the_configuration_in_docs_deploy_is_valid(tmp_path):
    # The file a user copies to /etc must load as it is written there.
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "docs" / "deploy.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1
    path = tmp_path / "rig.toml"
    path.write_text(blocks[0])
    cfg = load_config(path)
    assert cfg["source"]["camera"] == "opencv:0" and cfg["output"]["record"].endswith("{start}.mcap")


def test_a_ring_that_can_never_hold_a_full_window_is_refused():
    # Each value alone is in range; together they once streamed partial windows, every one
    # flagged invalid, without a word.
    check_window_fits(load_config(), 8)  # the defaults fit
    small = merge(load_config(), {"rig": {"ring_capacity": 4}})
    fewer = r"^\[rig\] ring_capacity: 4 frames is fewer than the model's window of 8.*8 or more$"
    with pytest.raises(ConfigError, match=fewer):
        check_window_fits(small, 8)
    check_window_fits(small, 4)
    short = merge(load_config(), {"rig": {"ring_max_age_s": 0.5}})
    with pytest.raises(ConfigError, match=r"^\[rig\] ring_max_age_s: 0.5 s is shorter than \[window\] span_s 4 s"):
        check_window_fits(short, 8)
    check_window_fits(merge(short, {"window": {"span_s": 0.5}}), 8)


def test_write_replacing_writes_a_device_or_fifo_in_place_and_a_file_whole(tmp_path):
    # Renamed over, `eval --json /dev/full` replaced the device itself with a regular file (found
    # when the disk-full tests that use /dev/full then passed). A FIFO stands in for the device.
    import os
    import stat
    import threading

    from rig.files import write_replacing

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    write_replacing(fifo, lambda p: p.write_text("through\n"))
    reader.join(5.0)
    assert got == ["through\n"] and stat.S_ISFIFO(os.stat(fifo).st_mode)
    plain = tmp_path / "out.json"
    plain.write_text("old")

    def torn(p):
        p.write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space left") as info:
        write_replacing(plain, torn)
    assert info.value.filename == str(plain) and plain.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json", "pipe"]  # no torn sibling left


def test_a_fifo_with_no_writer_is_refused_at_once_and_a_pipe_is_read(tmp_path):
    # `--config FIFO` with nothing writing into it blocked in open() for ever: `config --print`
    # hung, and a service never got as far as failing. A pipe that has a writer (`--config <(...)`)
    # is still read to its end.
    import os
    import threading

    fifo = tmp_path / "rig.toml"
    os.mkfifo(fifo)
    got: list = []

    def load():
        try:
            got.append(load_config(fifo))
        except ConfigError as exc:
            got.append(exc)

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(5.0)
    if reader.is_alive():  # unblock the open, so the thread ends
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(5.0)
        pytest.fail("load_config blocked on a FIFO nothing writes to")
    assert len(got) == 1 and isinstance(got[0], ConfigError), got
    assert str(got[0]) == (f"config file {fifo} is a pipe that nothing writes to; pass the .toml file itself, "
                           "or start its writer first")
    r, w = os.pipe()
    try:
        os.write(w, b"[window]\nspan_s = 5.0\n")
        os.close(w)
        w = -1
        assert load_config(f"/dev/fd/{r}")["window"]["span_s"] == 5.0
    finally:
        os.close(r)
        if w >= 0:
            os.close(w)


def test_a_file_saved_by_windows_notepad_loads(tmp_path):
    # A UTF-8 byte order mark (Notepad's "UTF-8 with BOM") was "not valid TOML: Invalid statement
    # (at line 1, column 1)", of a first line that looks right in every editor. CRLF line ends too.
    path = tmp_path / "rig.toml"
    path.write_bytes(b"\xef\xbb\xbf[source]\r\ncamera = \"opencv:0\"\r\n[window]\r\nspan_s = 5.0\r\n")
    cfg = load_config(path)
    assert cfg["source"]["camera"] == "opencv:0" and cfg["window"]["span_s"] == 5.0
    path.write_bytes(b"\xef\xbb\xbf[window]\nspan_s = \n")  # and a mistake in it is still placed right
    with pytest.raises(ConfigError, match=r"\(at line 2, column 10\)$"):
        load_config(path)


def test_a_byte_that_is_not_utf8_is_placed_by_line_and_column(tmp_path):
    # "(byte 873)" sent the user counting bytes; an editor goes to a line and column, as the TOML
    # errors give them. The column counts characters, as the editor does (é before it is one).
    path = tmp_path / "rig.toml"
    path.write_bytes("[source]\ncamera = 'é'\nheading = 'çam".encode() + b"\xe9ra'\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == (f"config file {path} is not UTF-8 text (line 3, column 15: byte 0xe9); "
                               "save it as UTF-8 TOML")
    path.write_bytes(b"\xef\xbb\xbf\xff")  # after a byte order mark: still line 1, column 1
    with pytest.raises(ConfigError, match=r"\(line 1, column 1: byte 0xff\)"):
        load_config(path)


@pytest.mark.parametrize("value", ["[" * 50_000 + "]" * 50_000, "{a = " * 5_000 + "1" + "}" * 5_000],
                         ids=["arrays", "tables"])
def test_a_value_nested_without_end_is_a_one_line_error(tmp_path, value):
    # Well under the size bound, it was "internal error: RecursionError" (exit 1), from the parser.
    path = tmp_path / "rig.toml"
    path.write_text(f"[source]\ncamera = {value}\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == (f"config file {path} nests arrays or tables too deeply for a config, which holds "
                               "[sections] of strings, numbers and booleans; sunrig config --print writes one")


def test_relative_paths_in_a_config_file_are_relative_to_its_folder(tmp_path, monkeypatch):
    # A service's working directory is / (systemd): `calibration = "camera.yaml"` beside
    # /etc/sunrig/rig.toml was looked for as /camera.yaml, and `jsonl = "est.jsonl"` written to
    # /, after `sunrig config --print` had passed in /etc/sunrig. Ports and URLs are as written.
    etc = tmp_path / "etc sunrig"
    etc.mkdir()
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    path = etc / "rig.toml"
    path.write_text('[source]\ncamera = "file:drives/d1.mcap"\ncalibration = "camera.yaml"\n'
                    'heading = "nmea:socket://10.0.0.5:2000"\n'
                    '[estimator]\nmodel = "../models/m1"\n'
                    '[output]\njsonl = "est.jsonl"\nrecord = "/var/lib/sunrig/{start}.mcap"\nserial = "/dev/ttyUSB1"\n')
    cfg = load_config(path)
    assert cfg["source"]["camera"] == f"file:{etc}/drives/d1.mcap"
    assert cfg["source"]["calibration"] == f"{etc}/camera.yaml"
    assert cfg["estimator"]["model"] == f"{etc}/../models/m1"
    assert cfg["output"]["jsonl"] == f"{etc}/est.jsonl"
    assert cfg["output"]["record"] == "/var/lib/sunrig/{start}.mcap"  # in full already
    assert cfg["source"]["heading"] == "nmea:socket://10.0.0.5:2000" and cfg["output"]["serial"] == "/dev/ttyUSB1"
    # A device index, a stream URL or a pipeline is no path; stdout (-) and "unset" ("") stay.
    for camera in ("opencv:0", "opencv:rtsp://cam/live", "opencv:v4l2src ! appsink", "oak"):
        path.write_text(f'[source]\ncamera = "{camera}"\n[output]\njsonl = "-"\n')
        cfg = load_config(path)
        assert (cfg["source"]["camera"], cfg["output"]["jsonl"], cfg["source"]["calibration"]) == (camera, "-", "")
    path.write_text('[source]\ncamera = "opencv:videos/drive.mp4"\n')
    assert load_config(path)["source"]["camera"] == f"opencv:{etc}/videos/drive.mp4"
    # What config --print writes reads back the same from any folder (the paths are in full).
    path.write_text('[source]\ncalibration = "camera.yaml"\n[output]\njsonl = "est.jsonl"\n')
    printed = tmp_path / "elsewhere" / "printed.toml"
    printed.write_text(dump_toml(load_config(path)))
    assert _same(load_config(printed), load_config(path))
    # A config from a pipe (--config <(...)) has no folder: its paths are the working directory's.
    import os

    r, w = os.pipe()
    try:
        os.write(w, b'[output]\njsonl = "est.jsonl"\n')
        os.close(w)
        assert load_config(f"/dev/fd/{r}")["output"]["jsonl"] == str(tmp_path / "elsewhere" / "est.jsonl")
    finally:
        os.close(r)


def test_docs_deploy_lists_every_option_with_its_default(tmp_path):
    # No doc listed the options ("`sunrig config --print` prints the full set"): [window]
    # yaw_scale_deg, [rig] ring_capacity and [source] heading_latency_s were named in none, and
    # [estimator] seed or [rig] queue_size only as other things' settings. The table must hold each
    # option once, no other, and its default as `config --print` writes it.
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "docs" / "deploy.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| `\[(\w+)\] (\w+)` \| `([^`]*)` \|", text, flags=re.M)
    listed = [(section, key) for section, key, _ in rows]
    assert len(listed) == len(set(listed)), "an option listed twice"
    options = [(section, key) for section, values in DEFAULTS.items() for key in values]
    assert sorted(listed) == sorted(options), (sorted(set(options) - set(listed)), sorted(set(listed) - set(options)))
    printed = tomllib.loads(dump_toml(DEFAULTS))
    for section, key, default in rows:
        assert _same(tomllib.loads(f"v = {default}")["v"], printed[section][key]), (section, key, default)


def _refused(tmp_path, text: str) -> tuple[object, str]:
    """A config file of ``text``, and what load_config's refusal of it says."""
    path = tmp_path / "rig.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    return path, str(info.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[source]\ncamera = 'bogus:0'\n", "[source] camera: expected oak, oak:DEVICE_ID, opencv:0, opencv:rtsp://..., "
                                           "opencv:VIDEO_FILE or file:LOG, got 'bogus:0'"),
        ("[source]\ncamera = 'opencv:'\n", "[source] camera: expected oak, "),
        ("[source]\ncamera = '  '\n", "[source] camera: expected oak, "),
        ("[source]\nheading = 'nmea'\n",
         "[source] heading: expected oak-imu, nmea:PORT, visual, none or log, got 'nmea'"),
        ("[source]\nheading = 'gps'\n",
         "[source] heading: expected oak-imu, nmea:PORT, visual, none or log, got 'gps'"),
        ("[source]\nheading = ''\n", "[source] heading: expected oak-imu, nmea:PORT, visual, none or log, got ''"),
    ],
)
def test_a_source_the_drivers_do_not_know_is_named_as_the_files_option(tmp_path, text, message):
    # `camera = "bogus:0"` passed `config --print` (which deploy.md says checks the file "as it would
    # be at boot"), and at boot was "--camera bogus:0: unknown camera", a flag the service never passed,
    # with no word of the file.
    path, said = _refused(tmp_path, text)
    assert said.startswith(f"{path}: {message}")


def test_every_source_the_drivers_know_loads_and_an_unset_camera_stays_unset(tmp_path):
    path = tmp_path / "rig.toml"
    for camera, heading in [("oak", "oak-imu"), ("oak:1844301011", "none"), ("opencv:0", "nmea:/dev/ttyUSB0"),
                            ("opencv:rtsp://cam/live", "visual"), ("file:/d/drive.mcap", "log"),
                            ("", "nmea:socket://10.0.0.5:2000")]:
        path.write_text(f'[source]\ncamera = "{camera}"\nheading = "{heading}"\n')
        cfg = load_config(path)
        assert (cfg["source"]["camera"], cfg["source"]["heading"]) == (camera, heading)


def test_a_ring_shorter_than_the_window_span_is_refused_as_the_file_is_read(tmp_path):
    # `[window] span_s = 12` (over the default ring_max_age_s of 10) passed `config --print`; `run`
    # refused it only after the camera had opened and the model loaded, without naming the file.
    # Neither option has a flag, so the file alone decides it.
    path = tmp_path / "rig.toml"
    path.write_text("[window]\nspan_s = 12.0\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == (f"{path}: [rig] ring_max_age_s: 10 s is shorter than [window] span_s 12 s, so frames "
                               "would leave the ring before a window could reach them; raise ring_max_age_s or "
                               "lower span_s")
    path.write_text("[window]\nspan_s = 12.0\n[rig]\nring_max_age_s = 12.0\n")
    assert load_config(path)["rig"]["ring_max_age_s"] == 12.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[output]\ncamera = 'oak'\n", "unknown option [output] camera: it is a [source] option; move it there"),
        ("[source]\nserial = '/dev/ttyUSB1'\n",
         "unknown option [source] serial: it is an [output] option; move it there"),
        ("[rig]\nbaud = 9600\n",
         "unknown option [rig] baud: it is a [source] or [output] option; move it there"),
        ("[source]\nrealtime = false\n", "unknown option [source] realtime: it is a [rig] option; move it there"),
    ],
)
def test_an_option_under_another_section_says_where_it_belongs(tmp_path, text, message):
    # It was refused as any typo is ("unknown option [output] camera; known: serial, baud, ..."),
    # a list without it, that left the user looking for the spelling mistake there was none of.
    path, said = _refused(tmp_path, text)
    assert said == f"{path}: {message}"


def test_the_service_in_docs_deploy_can_open_what_its_config_names(tmp_path):
    # The unit ran as a user in `dialout` alone: the page's own `camera = "opencv:0"` is /dev/video0,
    # the `video` group's ("no camera at index 0: ... that the user is in the 'video' group"), and its
    # recording folder /var/lib/sunrig/drives was made by nothing, nor writable by that user.
    import re
    import shutil
    import subprocess
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "docs" / "deploy.md").read_text(encoding="utf-8")
    [unit] = re.findall(r"```ini\n(.*?)```", text, flags=re.S)
    settings = dict(re.findall(r"^(\w+)=(.*)$", unit, flags=re.M))
    assert {"dialout", "video"} <= set(settings["SupplementaryGroups"].split())
    [config] = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    record = tomllib.loads(config)["output"]["record"]
    assert str(Path(record).parent) == f"/var/lib/{settings['StateDirectory']}"
    analyze = shutil.which("systemd-analyze")
    sunrig = shutil.which("sunrig")
    if analyze is None or sunrig is None:
        return  # the lines above are what a systemd-less machine can check
    path = tmp_path / "sunrig.service"  # with the ExecStart= path of this machine's sunrig
    path.write_text(unit.replace("/usr/local/bin/sunrig", sunrig))
    done = subprocess.run([analyze, "verify", str(path)], capture_output=True, text=True, timeout=60)
    # verify exits 0 for a setting it ignores ("Failed to parse ..., ignoring"): its lines say so.
    assert done.returncode == 0 and str(path) not in done.stderr, done.stderr


def test_every_rig_option_of_the_file_reaches_the_pipeline(tmp_path, monkeypatch, capsys):
    # [rig] max_latency_s was added to RigConfig but not to the file: the warning that names it
    # pointed at a setting no user could change. Each [rig] option must reach the pipeline.
    import rig.pipeline
    from replay.sources import DEMO_LOG
    from rig.cli import main

    seen = []
    real = rig.pipeline.RigPipeline

    class Spy(real):  # the real pipeline, its config kept to look at
        def __init__(self, *args, **kwargs):
            seen.append(kwargs["config"])
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(rig.pipeline, "RigPipeline", Spy)
    values = {"queue_size": 3, "ring_capacity": 64, "ring_max_age_s": 9.0, "status_every_s": 7.0,
              "max_latency_s": 2.5, "realtime": False}
    gate = {"max_covered_share": 0.5}  # the exposure gate's, which the pipeline is given whole
    assert set(values) | set(gate) == set(DEFAULTS["rig"])
    conf = tmp_path / "rig.toml"
    conf.write_text("[rig]\n" + "".join(f"{k} = {str(v).lower()}\n" for k, v in (values | gate).items()))
    assert main(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--config", str(conf), "--quiet",
                 "--jsonl", str(tmp_path / "o.jsonl")]) == 0
    (cfg,) = seen
    assert {k: getattr(cfg, k) for k in values} == values
    assert {k: getattr(cfg.exposure_gate, k) for k in gate} == gate


def test_a_latency_bound_shorter_than_the_pairings_wait_is_refused_for_a_compass():
    # A frame waits for the compass's next heading (up to [source] max_age_s, plus its latency):
    # under a [rig] max_latency_s shorter than that, the frames of a 1 Hz compass that waited
    # longest were all dropped as stale. Only where there is a pairing (an nmea: heading).
    from rig.config import ConfigError, check_window_fits, merge

    compass = merge(DEFAULTS, {"source": {"heading": "nmea:/dev/ttyUSB0", "heading_latency_s": 0.3},
                               "rig": {"max_latency_s": 1.7}})
    with pytest.raises(ConfigError, match=r"\[rig\] max_latency_s: 1.7 s is no longer than a frame may wait for "
                                          r"its heading \(\[source\] max_age_s 1.5 s \+ heading_latency_s 0.3 s\)"):
        check_window_fits(compass, 8)
    check_window_fits(merge(compass, {"rig": {"max_latency_s": 2.0}}), 8)
    check_window_fits(merge(compass, {"source": {"heading": "oak-imu"}}), 8)  # no pairing
    check_window_fits(DEFAULTS, 8)  # the defaults hold together
