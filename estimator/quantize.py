"""An int8 backbone: static quantization of a model folder's backbone graph with ONNX Runtime.

The backbone is where a frame's time goes; int8 weights and activations run its convolutions on
the CPU's integer dot-product instructions (AVX-512 VNNI on this machine). What that buys grows
with the network's width: measured by ``python3 benchmarks/bench_estimator.py --int8`` and written
down in docs/model.md ("int8"). Whether it holds accuracy is each model's own question: the result
is a model folder like any other, so ``sunrig eval --model`` answers it.

Activations are calibrated on crops the runtime itself cuts from the given logs (the model's crop
layout and angles, its input normalisation, and the flipped crops too when it runs mirrored), so
their ranges are those the rig will feed. Weights are quantized per output channel, activations
to uint8 (the fast path of ONNX Runtime's integer kernels on x86), in QDQ form, which ONNX
Runtime fuses into integer kernels when it loads the graph. The aggregator stays float32: it is a
small part of a frame's work, and it holds the attention softmax, where int8 loses most.

Needs the ``onnx`` package of the train extra; the runtime needs only onnxruntime, as for any
model.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from estimator.contract import (
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    BACKBONE_INPUT,
    CHECKPOINT,
    CHECKSUMS_FILE,
    METADATA_CONTRACT_KEY,
    WEIGHTS_FILE,
    format_checksums,
    set_metadata,
)
from rig.errors import MissingExtraError, ValidationError
from rig.files import check_folder_writable, folder_lock, make_output_folder, nearest_existing_folder, sync_to_disk
from rig.types import Frame

QUANTIZATION_KEY = "quantization"  # where the contract's training record says how a model was quantized
DEFAULT_CALIBRATION_CROPS = 1024
# The lock file of an --out being written (rig.files.folder_lock): hidden, and no model file.
QUANTIZE_LOCK = ".quantize.lock"
# The staging folder's prefix inside --out: what a run killed with -9 leaves behind.
_STAGING_PREFIX = ".quantize-"
# Crops a calibration run of the backbone takes at once. ONNX Runtime holds a run's activations in
# its arena until the end: quantizing the paper's architecture (224 px) peaked at 2.7 GB with 32,
# 1.8 GB with 8, in the same time.
_CALIBRATION_BATCH = 8

log = logging.getLogger(__name__)


def _require_onnx() -> Any:
    try:
        import onnx
        from onnxruntime import quantization  # imports onnx itself
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingExtraError(
            "quantizing a model needs the onnx package: install the train extra with `pip install 'sunrig[train]'`"
        ) from exc
    return onnx, quantization


def calibration_crops(estimator: Any, sources: Iterable[Iterable[Frame]], n_crops: int, seed: int = 0,
                      progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Up to ``n_crops`` crops [N, S, S, 3] uint8 BGR, as ``estimator`` (a
    :class:`estimator.estimator.SunEstimator`) cuts them for its model from these frames; the
    quantizer normalises them a batch at a time, as the runtime does, so that they are held at a
    byte a value rather than float32's four.

    The frames are a uniform draw from all the sources' frames (reservoir sampling, a reservoir
    of as many frames as the crops need), so the draw spans every log, not the first ones read,
    and only the kept frames' crops are held. ``progress(frames_read)`` is called after each frame."""
    if not isinstance(n_crops, int) or n_crops < 1:
        raise ValidationError(f"calibration crops: expected a positive integer, got {n_crops!r}")
    per_frame = estimator.backbone_crops_per_frame
    n_frames = max(1, math.ceil(n_crops / per_frame))
    rng = np.random.default_rng(seed)
    kept: list[np.ndarray] = []
    seen = 0
    for frames in sources:
        for frame in frames:
            seen += 1
            slot = seen - 1 if len(kept) < n_frames else int(rng.integers(seen))
            if slot < n_frames:
                crops = estimator.backbone_crops(frame)
                if slot == len(kept):
                    kept.append(crops)
                else:
                    kept[slot] = crops
            if progress is not None:
                progress(seen)
    if not kept:
        s = estimator.model.contract.crop_size_px
        return np.zeros((0, s, s, 3), np.uint8)
    return np.concatenate(kept)[:n_crops]


class _CalibrationReader:
    """onnxruntime's calibration data reader (it needs only ``get_next``) over crops as
    :func:`calibration_crops` gives them, a batch at a time, normalised as ``model`` feeds them."""

    def __init__(self, model: Any, crops: np.ndarray,
                 progress: Callable[[int, int], None] | None = None) -> None:
        self._model = model
        self._crops = crops
        self._at = 0
        self._progress = progress

    def get_next(self) -> dict[str, np.ndarray] | None:
        # Asked for the next batch once the last one has run: the crops before it are done.
        if self._progress is not None:
            self._progress(min(self._at, len(self._crops)), len(self._crops))
        if self._at >= len(self._crops):
            return None
        batch = self._crops[self._at : self._at + _CALIBRATION_BATCH]
        self._at += _CALIBRATION_BATCH
        return {BACKBONE_INPUT: self._model.normalise(batch)}


def _check_output(model: Any, out_dir: str | os.PathLike) -> Path:
    """``out_dir``, once it is known that quantizing ``model`` into it replaces nothing."""
    if QUANTIZATION_KEY in model.contract.training:
        raise ValidationError(f"{model.model_dir}: its backbone is int8 already; quantize the float model it was "
                              "made from")
    out = Path(out_dir)
    if out.is_dir() and out.resolve() == Path(model.model_dir).resolve():
        raise ValidationError(f"{out} is the model being quantized; pass a new folder as --out")
    _refuse_replacing(out)
    if out.exists() and not out.is_dir():
        raise ValidationError(f"{out} is a file; a model is a folder: pass a folder's path")
    check_folder_writable(out, flag="--out")  # before the logs are read
    _check_room(model, out)
    return out


def _refuse_replacing(out: Path) -> None:
    """Refuse an ``out`` holding a model, or a training run, whose files the int8 model's would
    replace or stand beside."""
    held = [name for name in (BACKBONE_FILE, AGGREGATOR_FILE, CHECKPOINT, WEIGHTS_FILE, CHECKSUMS_FILE)
            if (out / name).exists()]
    if held:
        raise ValidationError(f"{out} holds {held[0]} already; pass a new folder as --out, so that nothing is replaced")


def _bytes_needed(model: Any) -> int:
    """The most the staging holds at once on ``out``'s disk: the float backbone prepared, onnx's
    shape-inferred copy of it and the int8 graph (each at most the float one's size); then the int8
    graph, the aggregator and the weights, copied before they are moved into place."""
    src = Path(model.model_dir)

    def size(name: str) -> int:
        return (src / name).stat().st_size if (src / name).is_file() else 0

    backbone = size(BACKBONE_FILE)
    return max(3 * backbone, backbone + size(AGGREGATOR_FILE) + size(WEIGHTS_FILE))


def _check_room(model: Any, out: Path) -> None:
    """Refuse, before the logs are read, an ``out`` on a disk too full for the model: the write
    failed after the calibration, and some of its failures did not say the disk was full."""
    needed = _bytes_needed(model)
    free = shutil.disk_usage(nearest_existing_folder(out)).free
    if free < needed:
        raise ValidationError(f"--out {out}: writing the int8 model needs about {needed / 1e6:.1f} MB on its disk, "
                              f"{free / 1e6:.1f} MB free; free space there, or pass a folder on another disk")


def quantize_model(model: Any, calibration: np.ndarray, out_dir: str | os.PathLike, *,
                   record: dict[str, Any] | None = None,
                   calibration_progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``model`` (an :class:`estimator.runtime.OnnxModel`) to ``out_dir`` with an int8
    backbone calibrated on ``calibration`` (crops, as :func:`calibration_crops` gives them).

    The contract is the model's, with ``training.quantization`` saying what was done (plus
    ``record``: the command, the calibration data); both graphs carry it, ``SHA256SUMS`` covers
    them, and ``weights.npz`` (float, for fine-tuning) is copied. Files are staged and moved into
    place only when complete, as an export does. ``calibration_progress(crops_done, crops)`` is
    called as ONNX Runtime runs the float backbone over the crops, the longest part for a wide
    backbone."""
    onnx, quantization = _require_onnx()
    out = _check_output(model, out_dir)
    if len(calibration) == 0:
        raise ValidationError("no frames to calibrate on: pass logs that hold frames")
    model.normalise(calibration[:1])  # crops of this model's size, uint8, or a ValidationError now
    made = not out.exists()
    out = make_output_folder(out, what="model folder", holds="a model is a folder")
    try:
        # Held to the end: two runs into one --out staged side by side and moved their files over
        # each other's. Held, what an earlier run left staged is a killed run's (kill -9 skips
        # every cleanup), and a model that run finished meanwhile is not replaced.
        with folder_lock(out, name=QUANTIZE_LOCK, command="sunrig quantize", flag="--out"):
            _refuse_replacing(out)
            for debris in out.glob(_STAGING_PREFIX + "*"):
                if debris.is_dir():
                    shutil.rmtree(debris, ignore_errors=True)
            _write_quantized(model, calibration, out, onnx, quantization, record, calibration_progress)
    except BaseException:
        # Interrupted or failed (Ctrl-C during the minutes of calibration): a folder this run made
        # and left empty is neither a model nor absent; rmdir removes it only when empty.
        if made:
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    return out


def _write_quantized(model: Any, calibration: np.ndarray, out: Path, onnx: Any, quantization: Any,
                     record: dict[str, Any] | None, progress: Callable[[int, int], None] | None) -> None:
    contract = model.contract
    quantized = replace(contract, training={**contract.training, QUANTIZATION_KEY: {
        "backbone": "int8", "format": "QDQ", "activations": "uint8, calibrated (min-max)",
        "weights": "int8, per output channel", "from_model": model.model_id,
        "calibration_crops": len(calibration), **(record or {})}})
    with tempfile.TemporaryDirectory(dir=out, prefix=_STAGING_PREFIX) as tmp:
        try:
            _stage_and_move(model, quantized, calibration, Path(tmp), out, onnx, quantization, progress)
        except Exception as exc:
            if _filled_disk(exc, Path(tmp), _bytes_needed(model) // 3):
                # Said as a full disk where the model goes, which the command line tells the user
                # to free, whatever file (ours, onnx's) the failure named.
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(out)) from exc
            raise


_DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _filled_disk(exc: Exception, staging: Path, backbone_bytes: int) -> bool:
    """Whether ``exc``, raised while staging, is the staging disk filling up. A full disk's OSError
    may name the file read, not the one written (shutil.copyfile); onnx's C++ shape inference
    writes a graph cut short without a word, which then fails to parse, so any failure with less
    room left than a backbone graph takes counts. A full disk elsewhere (ONNX Runtime's own
    temporary files, in the system's temporary folder) is left to name its own path."""
    if isinstance(exc, OSError) and exc.errno in _DISK_FULL:
        named = [Path(os.fsdecode(f)) for f in (exc.filename, exc.filename2) if f is not None]
        return not named or any(p.resolve().is_relative_to(staging.resolve()) for p in named)
    try:
        return shutil.disk_usage(staging).free < backbone_bytes
    except OSError:
        return False


def _stage_and_move(model: Any, quantized: Any, calibration: np.ndarray, tmp: Path, out: Path, onnx: Any,
                    quantization: Any, progress: Callable[[int, int], None] | None) -> None:
    """Write the int8 model's files in ``tmp`` (a folder in ``out``) and move them into ``out``."""
    src = Path(model.model_dir)
    staged = {BACKBONE_FILE: tmp / BACKBONE_FILE, AGGREGATOR_FILE: tmp / AGGREGATOR_FILE}
    # ONNX Runtime's own preparation for its quantizer (shape inference, graph optimisation),
    # which the quantizer otherwise warns about.
    prepared = tmp / "prepared.onnx"
    quantization.quant_pre_process(str(src / BACKBONE_FILE), str(prepared))
    quantization.quantize_static(
        str(prepared), str(staged[BACKBONE_FILE]), _CalibrationReader(model, calibration, progress),
        quant_format=quantization.QuantFormat.QDQ, per_channel=True,
        activation_type=quantization.QuantType.QUInt8, weight_type=quantization.QuantType.QInt8,
        calibrate_method=quantization.CalibrationMethod.MinMax)
    prepared.unlink()  # room for the aggregator and the weights on a nearly full disk (_bytes_needed)
    for name, path in ((BACKBONE_FILE, staged[BACKBONE_FILE]), (AGGREGATOR_FILE, src / AGGREGATOR_FILE)):
        graph = onnx.load(str(path))
        # quantize_static keeps the graph's metadata (its role among it); the contract is
        # replaced in both graphs, so that they agree.
        set_metadata(graph, {METADATA_CONTRACT_KEY: quantized.to_json()})
        onnx.save(graph, str(staged[name]))
    digests = {name: hashlib.sha256(path.read_bytes()).hexdigest() for name, path in staged.items()}
    sums = tmp / CHECKSUMS_FILE
    sums.write_text(format_checksums(digests), encoding="utf-8")
    moved = {CHECKSUMS_FILE: sums, **staged}  # the sums first, as an export writes them
    if (src / WEIGHTS_FILE).is_file():
        shutil.copyfile(src / WEIGHTS_FILE, tmp / WEIGHTS_FILE)
        moved = {WEIGHTS_FILE: tmp / WEIGHTS_FILE, **moved}
    # Each file on the disk before it is renamed into place, and the renames after, as an export
    # does: renamed with their data still in memory, a power loss could leave empty files under
    # the model's names.
    for path in moved.values():
        sync_to_disk(path)
    for name, path in moved.items():
        os.replace(path, out / name)
    sync_to_disk(out)


def quantize_logs_model(model: Any, log_sources: Sequence[tuple[Path, Iterable[Frame]]], out_dir: str | os.PathLike,
                        *, n_crops: int = DEFAULT_CALIBRATION_CROPS, seed: int = 0, command: str = "",
                        progress: Callable[[int], None] | None = None,
                        calibration_progress: Callable[[int, int], None] | None = None) -> Path:
    """:func:`quantize_model` calibrated on the frames of ``log_sources`` ((path, frames) pairs),
    the crops cut as ``model`` runs (its crop layout, seed ``seed``). ``progress(frames_read)``
    while the logs are read, then ``calibration_progress(crops_done, crops)`` while the backbone
    runs over the crops."""
    from estimator.estimator import SunEstimator
    from estimator.recipe import data_fingerprint

    _require_onnx()  # both refused now, not after minutes of reading the logs
    _check_output(model, out_dir)
    estimator = SunEstimator(model, seed=seed)
    frames_read = 0

    def count(n_frames: int) -> None:
        nonlocal frames_read
        frames_read = n_frames
        if progress is not None:
            progress(n_frames)

    # Drawn from the logs in an order of their names, as the fingerprint counts them: the same logs
    # given in another order (another shell's glob) are the same calibration, and the same graph.
    ordered = sorted(log_sources, key=lambda source: (Path(source[0]).name, str(source[0])))
    calibration = calibration_crops(estimator, (frames for _, frames in ordered), n_crops, seed=seed,
                                    progress=count)
    if 0 < len(calibration) < n_crops:
        # Said, not refused: a few hundred crops still calibrate, but the contract alone said so.
        log.warning("quantize: the logs hold %d frames, %d crops of the %d asked; calibrating on those (more frames "
                    "like the rig's calibrate the int8 model better)", frames_read, len(calibration), n_crops)
    paths = [Path(p) for p, _ in log_sources]
    record = {"calibration_logs": len(paths), "calibration_fingerprint": data_fingerprint(paths),
              "calibration_seed": seed, **({"command": command} if command else {})}
    return quantize_model(model, calibration, out_dir, record=record, calibration_progress=calibration_progress)
