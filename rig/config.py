"""The rig's configuration: one TOML file covers every option; command-line flags override it.

Defaults live in :data:`DEFAULTS` (the single table of options, their types and defaults);
``sunrig config --print`` shows the effective configuration as TOML, which is also a valid
config file to start from.
"""

from __future__ import annotations

import codecs
import copy
import errno
import json
import math
import os
import stat
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rig.errors import SunrigError
from rig.types import MIN_FOV_DEG


class ConfigError(SunrigError):
    """A configuration file or option is wrong; the message names the option."""


# section -> option -> default. The type of each default is the option's type.
DEFAULTS: dict[str, dict[str, Any]] = {
    "source": {
        "camera": "",  # oak | opencv:N | opencv:URL | opencv:FILE | file:LOG (docs/drivers.md)
        "heading": "log",  # oak-imu | nmea:PORT | visual | none | log (a file: camera's own)
        "calibration": "",  # OpenCV calibration file; empty: the device's own or hfov_deg
        "hfov_deg": 0.0,  # horizontal field of view when there is no calibration; 0: unset
        "width": 0,  # requested frame size and rate; 0: the device's default
        "height": 0,
        "fps": 0.0,
        "baud": 115200,  # nmea: heading port
        "max_gap_s": 1.5,  # pairing (drivers/pairing.py)
        "max_age_s": 1.5,
        "heading_latency_s": 0.0,
        "declination_deg": float("nan"),  # oak-imu, east positive; nan: unset (heading stays magnetic)
    },
    "estimator": {
        "model": "",  # model folder; empty: the shipped default
        "aggregator": "transformer",
        "seed": 0,
    },
    "window": {
        "span_s": 4.0,
        "yaw_scale_deg": 45.0,
    },
    "rig": {
        "queue_size": 2,
        "ring_capacity": 128,
        "ring_max_age_s": 10.0,
        "status_every_s": 5.0,
        "max_latency_s": 2.0,  # an estimate later than this after its frame is not sent (rig.pipeline)
        "realtime": True,  # pace a recorded source by its timestamps
        # a frame more than this share of which is dark and flat (a cover) is left out (rig.exposure);
        # raise it for a camera that always sees its own hood or dashboard, 1: never
        "max_covered_share": 0.25,
    },
    "output": {
        "serial": "",  # port or pyserial URL; empty: no serial output
        "baud": 115200,
        "format": "nmea",
        "jsonl": "",  # path or - ; empty: none
        "record": "",  # MCAP path; empty: no recording
        "record_frames": False,  # record the frames too, not only the estimates
        "record_overwrite": False,  # replace an existing recording (by default it is refused)
    },
}

CHOICES = {
    ("estimator", "aggregator"): ("transformer", "mean", "meanshift", "single"),
    ("output", "format"): ("nmea", "binary"),
}

# The range of each number: (lowest, highest, lowest allowed itself?). Checked where the option is
# read (a file or the command line), so `sunrig config --print` and every command refuse the same
# values, before any device opens. 0 is "unset" where its comment says so, and so is nan where it
# is the default (TOML has no null).
_INF = float("inf")
POSITIVE = (0.0, _INF, False)
NON_NEGATIVE = (0.0, _INF, True)
RANGES: dict[tuple[str, str], tuple[float, float, bool]] = {
    ("source", "hfov_deg"): (0.0, 179.0, True),
    ("source", "width"): NON_NEGATIVE,
    ("source", "height"): NON_NEGATIVE,
    ("source", "fps"): NON_NEGATIVE,
    ("source", "baud"): POSITIVE,
    ("source", "max_gap_s"): POSITIVE,
    ("source", "max_age_s"): POSITIVE,
    ("source", "heading_latency_s"): NON_NEGATIVE,
    ("source", "declination_deg"): (-180.0, 180.0, True),
    ("estimator", "seed"): NON_NEGATIVE,
    ("window", "span_s"): POSITIVE,
    ("window", "yaw_scale_deg"): (0.0, 180.0, False),
    ("rig", "queue_size"): POSITIVE,
    ("rig", "ring_capacity"): POSITIVE,
    ("rig", "ring_max_age_s"): POSITIVE,
    ("rig", "status_every_s"): POSITIVE,
    ("rig", "max_latency_s"): POSITIVE,
    ("rig", "max_covered_share"): (0.0, 1.0, True),
    ("output", "baud"): POSITIVE,
}


# Options whose 0 is "unset" and whose other values start higher: a field of view narrower than any
# camera's (rig/types.py MIN_FOV_DEG) is a typo or a damaged number, and at 1e-300 deg a focal
# length whose crops overflowed.
NARROWEST: dict[tuple[str, str], tuple[float, str]] = {
    ("source", "hfov_deg"): (MIN_FOV_DEG, "deg, as any camera has"),
}


def describe_range(lo: float, hi: float, lo_included: bool) -> str:
    """``>= 0``, ``> 0`` or ``in [0, 179]``: how an error says what was expected."""
    def shown(x: float) -> str:  # INT_MAX in full, not 2.14748e+09
        return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"

    if hi == _INF:
        return f"{'>=' if lo_included else '>'} {shown(lo)}"
    return f"in {'[' if lo_included else '('}{shown(lo)}, {shown(hi)}]"


# The largest integer any option takes: each ends in a C int somewhere (OpenCV's frame size,
# termios' baud, a queue's length), and a 400-digit one is a typo that must not reach them.
INT_MAX = 2**31 - 1


def in_range(value: float, lo: float, hi: float, lo_included: bool) -> bool:
    """A finite ``value`` within the range (inf is never meant: a budget that never ends); an
    integer also at most :data:`INT_MAX`."""
    if isinstance(value, int):  # math.isfinite() overflows on a huge one
        hi = min(hi, INT_MAX)
    elif not math.isfinite(value):
        return False
    return (lo <= value if lo_included else lo < value) and value <= hi


def check_option(section: str, key: str, value: Any) -> Any:
    """``value`` for ``[section] key``, checked against its type, choices and range (ConfigError)."""
    default = DEFAULTS[section][key]
    expected = type(default)
    written = value  # as an error shows it
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            value = written = float(value)
        except OverflowError:  # a 400-digit integer, more than a float holds: out of range, shown as written
            value = math.inf if value > 0 else -math.inf
    if expected is float and value is None:
        value = float("nan")
    if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise ConfigError(f"[{section}] {key}: expected {expected.__name__}, got {shown_value(value)}")
    choices = CHOICES.get((section, key))
    if choices and value not in choices:
        raise ConfigError(f"[{section}] {key}: expected one of {', '.join(choices)}, got {shown_value(value)}")
    bounds = RANGES.get((section, key))
    unset = expected is float and math.isnan(default) and math.isnan(value)
    if bounds is not None and not unset and not in_range(value, *bounds):
        kind = "an integer" if expected is int else "a finite number"
        if expected is int and value > INT_MAX:  # the cap is named only to one who passed it
            bounds = (bounds[0], INT_MAX, bounds[2])
        raise ConfigError(f"[{section}] {key}: expected {kind} {describe_range(*bounds)}, got {shown_value(written)}")
    narrowest = NARROWEST.get((section, key))
    if narrowest is not None and 0 < value < narrowest[0]:
        raise ConfigError(f"[{section}] {key}: expected 0 (unset) or at least {narrowest[0]:g} {narrowest[1]}, "
                          f"got {shown_value(value)}")
    return value


def check_window_fits(cfg: Mapping[str, Mapping[str, Any]], frames_per_window: int) -> None:
    """Refuse a ring that can never hold a full window of the model's (ConfigError). Each option is
    in range alone (:func:`check_option`); together they would stream partial windows, all
    flagged invalid, for as long as the rig runs."""
    rig = cfg["rig"]
    if rig["ring_capacity"] < frames_per_window:
        raise ConfigError(
            f"[rig] ring_capacity: {rig['ring_capacity']} frames is fewer than the model's window of "
            f"{frames_per_window}, so no window would ever be full; set it to {frames_per_window} or more"
        )
    check_ring_keeps_span(cfg)
    check_latency_covers_pairing(cfg)


def check_latency_covers_pairing(cfg: Mapping[str, Mapping[str, Any]]) -> None:
    """Refuse (ConfigError) a bound on an estimate's age that the heading pairing alone can pass: a
    frame waits for the compass's next heading up to ``[source] max_age_s`` plus its
    ``heading_latency_s`` (drivers.pairing), and under a shorter ``[rig] max_latency_s`` the frames
    of a slow compass (1 Hz) that waited longest were all dropped as stale. Only with an ``nmea:``
    heading, the one that is paired."""
    source, rig = cfg["source"], cfg["rig"]
    if not str(source["heading"]).startswith("nmea:"):
        return
    wait_s = source["max_age_s"] + source["heading_latency_s"]
    if rig["max_latency_s"] <= wait_s:
        raise ConfigError(
            f"[rig] max_latency_s: {rig['max_latency_s']:g} s is no longer than a frame may wait for its heading "
            f"([source] max_age_s {source['max_age_s']:g} s + heading_latency_s {source['heading_latency_s']:g} s), "
            "so the frames that waited longest would be dropped as stale; raise max_latency_s above "
            f"{wait_s:g} s or lower max_age_s"
        )


def check_ring_keeps_span(cfg: Mapping[str, Mapping[str, Any]]) -> None:
    """Refuse a ring that lets frames go before a window's span has passed (ConfigError). Needs no
    model, so :func:`load_config` checks it as the file is read (no flag sets either option)."""
    rig, window = cfg["rig"], cfg["window"]
    if rig["ring_max_age_s"] < window["span_s"]:
        raise ConfigError(
            f"[rig] ring_max_age_s: {rig['ring_max_age_s']:g} s is shorter than [window] span_s "
            f"{window['span_s']:g} s, so frames would leave the ring before a window could reach them; "
            "raise ring_max_age_s or lower span_s"
        )


def shown_value(value: Any) -> str:
    """``value`` for an error line: a 400-digit number is cut, so the message stays one line."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:20]}... ({len(text)} characters)"


MAX_CONFIG_BYTES = 2**20


class _NoWriter(Exception):
    """A pipe (FIFO) that nothing writes to."""


def _read_bounded(path: str | Path) -> bytes:
    """The file's bytes, at most ``MAX_CONFIG_BYTES + 1`` of them: a rig's config is a few hundred
    bytes, and --config /dev/zero (or a wrong file that never ends) grew by gigabytes until the
    machine killed the command.

    Opened without blocking: a FIFO that nothing writes to blocked open() for ever (a service that
    never even failed). A pipe with a writer (``--config <(...)``) is then read to its end."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        chunks = []
        if stat.S_ISFIFO(mode):
            try:
                first = os.read(fd, MAX_CONFIG_BYTES + 1)
            except BlockingIOError:  # a writer, that has not written yet: wait for it below
                first = None
            if first == b"":  # end of file at once: no writer (Linux counts one still opening)
                raise _NoWriter
            if first is not None:
                chunks.append(first)
        os.set_blocking(fd, True)
        size = sum(map(len, chunks))
        while size <= MAX_CONFIG_BYTES:
            chunk = os.read(fd, MAX_CONFIG_BYTES + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def load_config(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """Defaults, updated by the TOML file at ``path`` when given."""
    cfg = copy.deepcopy(DEFAULTS)
    if path is None:
        return cfg
    try:
        data = _read_bounded(path)
        if len(data) > MAX_CONFIG_BYTES:
            raise ConfigError(f"config file {path} is over {MAX_CONFIG_BYTES // 2**20} MiB, which no config is; "
                              "pass the --config FILE.toml written for the rig (sunrig config --print makes one)")
        # A UTF-8 byte order mark (Notepad's "UTF-8 with BOM") is no part of the text; TOML took it
        # for a character of the first line, a mistake no editor shows.
        if data.startswith(codecs.BOM_UTF8):
            data = data[len(codecs.BOM_UTF8):]
        raw = tomllib.loads(data.decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist; pass an existing --config FILE.toml") from None
    except _NoWriter:
        raise ConfigError(f"config file {path} is a pipe that nothing writes to; pass the .toml file itself, "
                          "or start its writer first") from None
    except IsADirectoryError:
        raise ConfigError(f"config file {path} is a folder; pass the .toml file in it") from None
    except UnicodeDecodeError as exc:
        # Placed by line and column, as the TOML errors are and an editor goes to: not by byte.
        before = exc.object[:exc.start]
        line_start = before.rfind(b"\n") + 1
        line = before.count(b"\n") + 1
        column = len(before[line_start:].decode("utf-8")) + 1  # in characters, as an editor counts
        raise ConfigError(f"config file {path} is not UTF-8 text (line {line}, column {column}: "
                          f"byte 0x{exc.object[exc.start]:02x}); save it as UTF-8 TOML") from None
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}; check its permissions") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    except RecursionError:  # tomllib descends once per level: `[[[[...` a few thousand deep, well under the bound
        raise ConfigError(f"config file {path} nests arrays or tables too deeply for a config, which holds "
                          "[sections] of strings, numbers and booleans; sunrig config --print writes one") from None
    cfg = merge(cfg, raw, where=str(path))
    for key in ("camera", "heading"):
        if key in raw.get("source", {}):
            _check_source_spec(key, cfg["source"][key], where=str(path))
    try:  # here, not at boot after the camera has opened and the model loaded, and naming the file
        check_ring_keeps_span(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    # The folder the file really is in (--config /dev/stdin < rig.toml included); a pipe has none.
    real = os.path.realpath(path)
    folder = os.path.dirname(real) if os.path.isfile(real) else os.getcwd()
    for section, key in PATH_OPTIONS:
        if key in raw.get(section, {}):
            cfg[section][key] = _in_folder(key, cfg[section][key], folder)
    return cfg


def _check_source_spec(key: str, value: str, where: str) -> None:
    """Refuse a ``[source] camera`` or ``heading`` that the drivers cannot parse (ConfigError).
    Checked as the file is read, so `config --print` refuses what boot would; at boot the drivers'
    own error named the flag (``--camera bogus:0``) a service never passed, and not the file.
    Only a file's values: a flag's are named by the drivers as the flag. The pair (a log's heading
    with a live camera) is not checked here: a flag may still change either."""
    from drivers.sources import CAMERA_HELP, HEADING_HELP, parse_camera, parse_heading

    if key == "camera" and value == "":  # unset, the default: `run` asks for one
        return
    parse, expected = (parse_camera, CAMERA_HELP) if key == "camera" else (parse_heading, HEADING_HELP)
    try:
        parse(value)
    except SunrigError:
        raise ConfigError(f"{where}: [source] {key}: expected {expected}, got {shown_value(value)}") from None


# The options that name a file or folder. Relative in a config file, they are relative to the
# file's folder: a service's working directory is / (systemd), so `calibration = "camera.yaml"`
# beside /etc/sunrig/rig.toml was /camera.yaml there, after `config --print` had passed in
# /etc/sunrig. They are made absolute as the file is read, so `config --print` writes them in
# full and its output reads back the same from anywhere. Ports (serial, nmea:) and URLs are
# taken as written.
PATH_OPTIONS = (("source", "camera"), ("source", "calibration"), ("estimator", "model"),
                ("output", "jsonl"), ("output", "record"))


def _in_folder(key: str, value: str, folder: str) -> str:
    """``value`` of option ``key`` with a relative path in it joined to ``folder``."""
    prefix = ""
    if key == "camera":  # file:LOG, or opencv:VIDEO (not an index, URL or GStreamer pipeline)
        kind, _, target = value.partition(":")
        is_file = kind == "file" or (kind == "opencv" and not target.isdigit() and "://" not in target
                                     and "!" not in target)
        if not is_file:
            return value
        prefix, value = f"{kind}:", target
    if not value or value == "-" or os.path.isabs(value):  # unset, stdout (jsonl), or in full already
        return prefix + value
    return prefix + os.path.join(folder, value)


def merge(cfg: dict[str, dict[str, Any]], raw: Mapping[str, Any], where: str = "config") -> dict:
    """``cfg`` updated by a nested mapping; unknown sections or options are errors, not ignored."""
    for section, values in raw.items():
        if section not in DEFAULTS:
            homes = [name for name, options in DEFAULTS.items() if section in options]
            if homes and not isinstance(values, Mapping):  # `camera = "oak"` above every [section]
                raise ConfigError(f"{where}: {section} is outside any section; put it under "
                                  + " or ".join(f"[{home}]" for home in homes))
            raise ConfigError(f"{where}: unknown section [{section}]; known: {', '.join(DEFAULTS)}")
        if not isinstance(values, Mapping):
            raise ConfigError(f"{where}: [{section}] must be a table of options")
        for key, value in values.items():
            if key not in DEFAULTS[section]:
                # An option of another section is no typo: its list of known names would not have it.
                homes = [name for name, options in DEFAULTS.items() if key in options]
                if homes:
                    article = "an" if homes[0][0] in "aeiou" else "a"
                    raise ConfigError(f"{where}: unknown option [{section}] {key}: it is {article} "
                                      + " or ".join(f"[{home}]" for home in homes) + " option; move it there")
                raise ConfigError(
                    f"{where}: unknown option [{section}] {key}; known: {', '.join(DEFAULTS[section])}"
                )
            try:
                cfg[section][key] = check_option(section, key, value)
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None  # which file (or the command line)
    return cfg


def override(cfg: dict[str, dict[str, Any]], flags: Mapping[str, Any]) -> dict:
    """Apply command-line flags given as ``{"section.key": value}``; None means "not given"."""
    nested: dict[str, dict[str, Any]] = {}
    for dotted, value in flags.items():
        if value is None:
            continue
        section, key = dotted.split(".", 1)
        nested.setdefault(section, {})[key] = value
    return merge(cfg, nested, where="command line")


def dump_toml(cfg: Mapping[str, Mapping[str, Any]]) -> str:
    """The configuration as TOML (flat sections of strings, numbers and booleans)."""
    lines = []
    for section, values in cfg.items():
        lines.append(f"[{section}]")
        for key, value in values.items():
            if isinstance(value, bool):
                text = "true" if value else "false"
            elif isinstance(value, str):
                # JSON's escapes are TOML's; TOML also wants DEL escaped, which JSON leaves raw.
                text = json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
            else:
                text = repr(value)
            lines.append(f"{key} = {text}")
        lines.append("")
    return "\n".join(lines)
