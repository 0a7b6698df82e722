"""The model contract: what a model folder promises, carried inside both ONNX graphs.

A model is a folder with ``backbone.onnx`` and ``aggregator.onnx`` and nothing executable. Each
graph stores the contract as JSON under the metadata key ``sunrig.contract`` and its role under
``sunrig.graph``. The runtime reads both back with onnxruntime alone, checks they agree with each
other and with the graphs' own inputs, and refuses a model that does not fit, naming what differs.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any, TypeGuard

import numpy as np

from rig.errors import ContractMismatch

_FLOAT32_MAX = float(np.finfo(np.float32).max)  # the crops are normalised in float32

CONTRACT_VERSION = 1
METADATA_CONTRACT_KEY = "sunrig.contract"
METADATA_GRAPH_KEY = "sunrig.graph"

BACKBONE_FILE = "backbone.onnx"
AGGREGATOR_FILE = "aggregator.onnx"
CHECKPOINT = "checkpoint.pt"  # a `sunrig train --out` folder's run, not a model until exported
WEIGHTS_FILE = "weights.npz"  # the float weights a fine-tune starts from (`--init`); the runtime never reads them
# sha256sum's format (``sha256sum -c SHA256SUMS`` checks a folder by hand): a graph damaged in a
# copy can still parse and run, and would answer wrong without a word.
CHECKSUMS_FILE = "SHA256SUMS"


def format_checksums(digests: dict[str, str]) -> str:
    return "".join(f"{digest}  {name}\n" for name, digest in sorted(digests.items()))


def set_metadata(model: Any, entries: dict[str, str]) -> None:
    """Set ``metadata_props`` keys on an ONNX model (an ``onnx.ModelProto``) in place, replacing
    existing values and keeping the others. Here, not in the exporter, so that rewriting a graph's
    contract (``estimator.quantize``) needs the onnx package but not torch."""
    keep = [p for p in model.metadata_props if p.key not in entries]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    for key, value in entries.items():
        model.metadata_props.add(key=key, value=value)


def parse_checksums(text: str) -> dict[str, str]:
    """File name -> hex digest, from sha256sum's output (``HEX  NAME`` or ``HEX *NAME``)."""
    out = {}
    for line in text.splitlines():
        digest, _, name = line.strip().partition(" ")
        name = name.strip().lstrip("*").removeprefix("./")  # `sha256sum ./*.onnx` writes ./NAME
        if len(digest) == 64 and name:
            out[name] = digest.lower()
    return out

# Graph input and output names, part of the contract.
BACKBONE_INPUT = "crops"  # [N, 3, S, S] float32, normalised as input_norm says
BACKBONE_OUTPUT = "embeddings"  # [N, D] float32
AGG_INPUT_EMBEDDINGS = "embeddings"  # [B, T, D] float32
AGG_INPUT_ANGLES = "angles"  # [B, T, 3] float32: yaw, horizontal, vertical view angle (rad)
AGG_INPUT_MASK = "mask"  # [B, T] bool: True where the token is real
AGG_OUTPUT = "sun_heading"  # [B, T, 3] float32: per-token sun vector in its heading frame

# KITTI's image_02 (fx = 721.5377) cropped at 224 px native: the paper's angular coverage per crop.
PAPER_CROP_FOV_DEG = math.degrees(2.0 * math.atan(112.0 / 721.5377))
PAPER_CROPS_PER_FRAME = 4  # 32 crops from 8 frames (paper Sec. 4)
# Upper bounds of a contract's sizes, far above any model made here (the shipped one runs 8 crops a
# frame, 8 frames, 96 px crops): a damaged or hand-edited contract asking for 100 000 crops a frame
# ran the runtime out of memory (killed, no message) instead of being refused.
MAX_CROPS_PER_FRAME = 256
MAX_FRAMES_PER_WINDOW = 64
MAX_CROP_SIZE_PX = 1024
MAX_EMBEDDING_DIM = 8192
YAW_INPUT = "relative-to-newest-frame"
# What to do about an invalid contract. `sunrig train --init` names its own flag in its place
# (estimator.train._checked_init): train has no --model.
CONTRACT_REMEDY = "re-export the model from its training run, or pass another --model"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def fovs_deg(value: float | Sequence[float]) -> tuple[float, ...]:
    """A crop angle setting (one angle, or one per scale) as a tuple of angles; 0 or empty: ()."""
    if isinstance(value, int | float):
        return (float(value),) if value else ()
    return tuple(float(v) for v in value)


def is_crop_fov_deg(value: object) -> bool:
    """Whether ``value`` is an angle a crop can span: a number in (0, 180) deg (nan is not;
    2 fx tan(90 deg) is no crop at all). The contract, ``sunrig train`` and its CLI all ask this."""
    return isinstance(value, int | float) and not isinstance(value, bool) and 0.0 < value < 180.0


def format_fovs_deg(value: float | Sequence[float]) -> str:
    """A crop angle setting as ``--crop-fov`` takes it: ``17.6`` or ``17.6,26``."""
    return ",".join(f"{v:g}" for v in fovs_deg(value)) or "0"


def _encoding_default() -> dict[str, Any]:
    # yaw_input: the yaw angle fed to the encoding is relative to the window's newest frame, so
    # the network cannot depend on a global yaw offset (estimator.estimator.window_tokens).
    return {
        "kind": "cyclic-nested-sine",
        "alpha": 32.0,
        "base": 10000.0,
        "depth_per_angle": 170,
        "yaw_input": YAW_INPUT,
    }


def _input_norm_default() -> dict[str, Any]:
    return {"color_order": "RGB", "scale": 1.0 / 255.0, "mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}


@dataclass(frozen=True)
class ModelContract:
    """Everything the runtime must know to feed a model and read its answer.

    ``crop_fov_deg`` is the horizontal angle a crop spans in the source image: the runtime cuts
    ``2 fx tan(fov / 2)`` pixels and resizes to ``crop_size_px``, so a model sees the same angular
    detail whatever the camera's resolution or focal length. A list of angles mixes scales in
    every frame: the frame's crops are shared out among the angles as evenly as they go, the first
    angle first (:func:`estimator.crops.crops_per_scale`), so narrow crops see shading and shadow
    detail and wide ones the layout of sky and street (docs/model.md). A runtime that predates
    lists refuses such a model rather than misreading it.

    ``mirror_windows``: the runtime also runs every window mirrored left to right (each crop
    flipped, headings and horizontal view angles negated, as training mirrors windows) and
    averages the two runs' answers, turned back into this world. A mirrored street is a real
    street lit by the mirrored sun, so the second run is a second look, not a guess; it costs
    twice the backbone and aggregator work (docs/model.md, "Mirrored at run time").
    """

    crop_size_px: int
    embedding_dim: int
    crop_fov_deg: float | list[float] = PAPER_CROP_FOV_DEG
    crops_per_frame: int = PAPER_CROPS_PER_FRAME
    frames_per_window: int = 8
    mirror_windows: bool = False
    encoding: dict[str, Any] = field(default_factory=_encoding_default)
    input_norm: dict[str, Any] = field(default_factory=_input_norm_default)
    architecture: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    version: int = CONTRACT_VERSION

    def __post_init__(self) -> None:
        problems = []
        for name, most in (("crop_size_px", MAX_CROP_SIZE_PX), ("embedding_dim", MAX_EMBEDDING_DIM),
                           ("crops_per_frame", MAX_CROPS_PER_FRAME), ("frames_per_window", MAX_FRAMES_PER_WINDOW)):
            v = getattr(self, name)
            if not _is_int(v) or not 0 < v <= most:  # JSON's true is not 1 frame
                problems.append(f"{name}: expected an integer from 1 to {most}, got {v!r}")
        if not isinstance(self.mirror_windows, bool):
            problems.append(f"mirror_windows: expected true or false, got {self.mirror_windows!r}")
        fovs = self.crop_fov_deg
        if isinstance(fovs, tuple):  # JSON has no tuples: a list keeps to_json/from_json/differences exact
            object.__setattr__(self, "crop_fov_deg", fovs := list(fovs))
        if isinstance(fovs, list) and len(fovs) == 1:
            object.__setattr__(self, "crop_fov_deg", fovs := fovs[0])  # one scale is written as a number
        angles = fovs if isinstance(fovs, list) else [fovs]
        if not angles or not all(is_crop_fov_deg(f) for f in angles):
            problems.append(f"crop_fov_deg: expected an angle or a list of angles within (0, 180) deg, got {fovs!r}")
        if self.version != CONTRACT_VERSION:
            problems.append(f"version: this runtime reads contract version {CONTRACT_VERSION}, got {self.version!r}")
        # The nested parts are read with .get() and [] everywhere: one that is not an object, or a
        # value of the wrong type in it, was an AttributeError or a KeyError at load, not this error.
        for name in ("encoding", "input_norm", "architecture", "training"):
            if not isinstance(getattr(self, name), dict):
                problems.append(f"{name}: expected a JSON object, got {getattr(self, name)!r}")
        if isinstance(self.encoding, dict):
            problems += _encoding_problems(self.encoding)
        if isinstance(self.input_norm, dict):
            problems += _input_norm_problems(self.input_norm)
        if problems:
            raise ContractMismatch("invalid model contract: " + "; ".join(problems) + "; " + CONTRACT_REMEDY)

    @property
    def crop_fovs_deg(self) -> tuple[float, ...]:
        """The crop angles as a tuple, one entry per scale (a single-scale model has one)."""
        return fovs_deg(self.crop_fov_deg)

    @property
    def tokens_per_window(self) -> int:
        return self.crops_per_frame * self.frames_per_window

    @property
    def trained_sun_elevation_deg(self) -> tuple[float, float] | None:
        """The lowest and highest true sun of the training data (deg above the horizon), which
        ``sunrig train`` records; None for a contract without it (an older or a hand-made model).

        A fine-tuned model's training data includes that of the model it started from (``init``):
        its weights began as that model's, and a few hundred steps on one's own drives do not
        unlearn the suns it saw. Without this, a model fine-tuned on drives with the sun at 15 deg
        flagged every sun above 20 deg as beyond its training."""
        data = self.training.get("data")
        init = self.training.get("init")
        init_range = None
        if isinstance(init, dict):
            # The start's own chain (recorded since session 11), else its training data's range.
            init_data = init.get("data")
            init_range = init.get("sun_elevation_deg") or (
                init_data.get("sun_elevation_deg") if isinstance(init_data, dict) else None)
        ranges = [r for r in (_elevation_range(data.get("sun_elevation_deg") if isinstance(data, dict) else None),
                              _elevation_range(init_range))
                  if r is not None]
        if not ranges:
            return None
        return min(r[0] for r in ranges), max(r[1] for r in ranges)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str, where: str = "model") -> ModelContract:
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ContractMismatch(f"{where}: the contract metadata is not JSON ({exc}); re-export the model") from None
        if not isinstance(raw, dict):
            raise ContractMismatch(f"{where}: the contract metadata is not a JSON object; re-export the model")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise ContractMismatch(
                f"{where}: the contract has fields this runtime does not know ({', '.join(unknown)}); "
                "upgrade sunrig or re-export the model"
            )
        try:
            return cls(**raw)
        except TypeError as exc:
            raise ContractMismatch(f"{where}: incomplete contract ({exc}); re-export the model") from None
        except ContractMismatch as exc:
            raise ContractMismatch(f"{where}: {exc}") from None

    def differences(self, other: ModelContract) -> list[str]:
        """Fields where two contracts disagree, as ``name: a != b`` strings (empty if identical)."""
        out = []
        a, b = asdict(self), asdict(other)
        for key in sorted(a):
            if a[key] != b[key]:
                out.append(f"{key}: {a[key]!r} != {b[key]!r}")
        return out


def input_affine(input_norm: dict[str, Any]) -> tuple[bool, list[float], list[float]]:
    """The contract's input normalisation as ``x = raw * gain + offset`` per channel.

    Returns (swap red and blue, gain[3], offset[3]) for uint8 BGR input, channels in the model's
    order. Runtime and training both use this, so they cannot drift apart.
    """
    swap = input_norm["color_order"] == "RGB"
    scale = float(input_norm["scale"])
    mean = [float(m) for m in input_norm["mean"]]
    std = [float(s) for s in input_norm["std"]]
    gain = [scale / s for s in std]
    offset = [-m / s for m, s in zip(mean, std, strict=True)]
    return swap, gain, offset


def _encoding_problems(enc: dict[str, Any]) -> list[str]:
    problems = [f"encoding.{key}: missing" for key in ("alpha", "base", "depth_per_angle") if key not in enc]
    for key in ("alpha", "base"):
        if key in enc and not _is_positive_number(enc[key]):
            problems.append(f"encoding.{key}: expected a finite number > 0, got {enc[key]!r}")
    depth = enc.get("depth_per_angle")
    if "depth_per_angle" in enc and not (_is_int(depth) and depth > 0 and depth % 2 == 0):
        problems.append(f"encoding.depth_per_angle: expected an even number > 0, got {depth!r}")
    if enc.get("kind") != "cyclic-nested-sine":
        problems.append(f"encoding.kind: expected 'cyclic-nested-sine', got {enc.get('kind')!r}")
    if enc.get("yaw_input") != YAW_INPUT:
        problems.append(f"encoding.yaw_input: this runtime feeds {YAW_INPUT!r}, got {enc.get('yaw_input')!r}")
    return problems


def _input_norm_problems(norm: dict[str, Any]) -> list[str]:
    problems = []
    if norm.get("color_order") not in ("RGB", "BGR"):
        problems.append(f"input_norm.color_order: expected 'RGB' or 'BGR', got {norm.get('color_order')!r}")
    if not _is_positive_number(norm.get("scale")):
        problems.append(f"input_norm.scale: expected a finite number > 0, got {norm.get('scale')!r}")
    mean, std = norm.get("mean"), norm.get("std")
    if not (isinstance(mean, list | tuple) and len(mean) == 3 and all(_is_number(m) for m in mean)):
        problems.append(f"input_norm.mean: expected 3 finite numbers, got {mean!r}")
    if not (isinstance(std, list | tuple) and len(std) == 3 and all(_is_positive_number(v) for v in std)):
        problems.append(f"input_norm.std: expected 3 finite numbers > 0, got {std!r}")  # each divides
    if not problems:
        # The crops are normalised in float32: a gain or offset beyond its range (a scale of 1e300,
        # a std of 1e-300) would feed the graphs inf and every window would fail on NaN.
        _, gain, offset = input_affine(norm)
        if not all(abs(g) * 255.0 + abs(o) < _FLOAT32_MAX for g, o in zip(gain, offset, strict=True)):
            problems.append(
                f"input_norm: scale {norm['scale']!r}, mean {mean!r} and std {std!r} give pixel values beyond float32"
            )
    return problems


def _is_int(v: Any) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _is_positive_number(v: Any) -> bool:
    return _is_number(v) and v > 0


def _elevation_range(rng: Any) -> tuple[float, float] | None:
    """A recorded ``[lowest, highest]`` sun elevation (deg), or None when it is not one."""
    if (isinstance(rng, list | tuple) and len(rng) == 2
            and all(isinstance(x, int | float) and -90.0 <= x <= 90.0 for x in rng) and rng[0] <= rng[1]):
        return float(rng[0]), float(rng[1])
    return None
