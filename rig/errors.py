"""One small exception tree. Every message says what is wrong and what to do about it.

The CLI prints ``str(error)`` of any :class:`SunrigError` as one line and exits non-zero; anything
else is a bug and gets a traceback only with ``--debug``.
"""

from __future__ import annotations

# What to do about a damaged file that came with sunrig itself (the shipped model, the demo log).
REINSTALL = ("reinstall sunrig (python3 -m pip install --force-reinstall --no-deps sunrig; in a source checkout, "
             "git checkout the file)")


class SunrigError(Exception):
    """Base of every error a user can cause or fix (bad input, wrong model, missing device)."""


class ValidationError(SunrigError, ValueError):
    """A value handed to a core type does not fit (shape, dtype, range or unit)."""


class LogError(SunrigError):
    """A log file cannot be read: not a log, corrupt, or missing the channels a replay needs."""


class EmptyLogError(LogError):
    """A log that holds no frames: its recording stopped, or was cut off, before the first frame
    was written (a power cut at start-up). ``eval`` and ``train`` over many logs skip such a log
    with a warning, as there is nothing in it to lose; a log given alone is an error.

    ``name`` is the log as given and ``reason`` what it is, e.g. "an MCAP log cut off before its
    first complete chunk", for a warning that words the remedy its own way.
    """

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"{name} holds no frames ({reason}); record again or pass another log")
        self.name, self.reason = name, reason


class ModelError(SunrigError):
    """A model folder cannot be used: missing graph, unreadable file, or no contract."""


class ContractMismatch(ModelError):
    """A model's contract does not fit what the runtime or the other graph expects."""


class MissingExtraError(SunrigError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


class ProtocolError(SunrigError, ValueError):
    """Bytes from a wire are not a message this decoder can use (``docs/protocol.md``).

    ``reason`` says which check failed, so a stream reader can count each kind apart:
    ``"checksum"`` (NMEA XOR or CRC-16), ``"framing"`` (no ``$``/``*HH``, bad COBS, wrong length),
    ``"version"`` (a protocol version or message type this decoder does not know),
    ``"foreign"`` (a valid NMEA sentence that is not ours) or ``"field"`` (a field out of range).
    """

    def __init__(self, message: str, reason: str = "framing") -> None:
        super().__init__(message)
        self.reason = reason


class DeviceError(SunrigError):
    """A device source or sink cannot be opened or used. Raised at start-up; live, the device
    workers retry with backoff and count failures instead (``rig.portio``)."""


class GnssError(DeviceError):
    """A GNSS/INS source cannot be opened or used: no such device or file, no permission, a bad option."""


class CameraError(DeviceError):
    """A camera cannot be opened or used: no such device, file or stream, no intrinsics, a bad option."""


class OakError(CameraError):
    """The OAK source cannot be opened or used: no device, no calibration, a bad option, a lost device."""


class SourceError(SunrigError):
    """A ``--camera`` / ``--heading`` spec is unknown, incomplete, or the two do not go together."""


class PublishError(DeviceError):
    """A publisher cannot start or be used: the serial port cannot be opened, a bad option, closed."""


def require_torch():
    """Import torch lazily, naming the extra to install when it is absent."""
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingExtraError(
            "this needs PyTorch: install the train extra with `pip install 'sunrig[train]'`"
        ) from exc
    return torch
