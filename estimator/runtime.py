"""Run a model folder with onnxruntime: the backbone per frame, the aggregator per window.

numpy + onnxruntime only, never torch: this is what runs on the rig. Loading checks the folder
against the contract each graph carries (see :mod:`estimator.contract`) and refuses, with a
one-line message naming the difference and the fix, anything that does not fit.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from estimator.contract import (
    AGG_INPUT_ANGLES,
    AGG_INPUT_EMBEDDINGS,
    AGG_INPUT_MASK,
    AGG_OUTPUT,
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    BACKBONE_INPUT,
    BACKBONE_OUTPUT,
    CHECKPOINT,
    CHECKSUMS_FILE,
    CONTRACT_VERSION,
    METADATA_CONTRACT_KEY,
    METADATA_GRAPH_KEY,
    ModelContract,
    input_affine,
    parse_checksums,
)
from rig.errors import REINSTALL, ContractMismatch, ModelError, ValidationError

ROLES = {BACKBONE_FILE: "backbone", AGGREGATOR_FILE: "aggregator"}
DEFAULT_EMBED_BATCH = 32  # one paper window's worth of crops; bounds peak memory per run

# What each graph must expose: name -> (onnx element type, shape with None for free axes).
# "S" and "D" stand for the contract's crop size and embedding width.
_BACKBONE_IO = {
    "inputs": {BACKBONE_INPUT: ("tensor(float)", (None, 3, "S", "S"))},
    "outputs": {BACKBONE_OUTPUT: ("tensor(float)", (None, "D"))},
}
_AGGREGATOR_IO = {
    "inputs": {
        AGG_INPUT_EMBEDDINGS: ("tensor(float)", (None, None, "D")),
        AGG_INPUT_ANGLES: ("tensor(float)", (None, None, 3)),
        AGG_INPUT_MASK: ("tensor(bool)", (None, None)),
    },
    "outputs": {AGG_OUTPUT: ("tensor(float)", (None, None, 3))},
}


def session_options(intra_op_threads: int | None = None, *, spin_wait: bool = False) -> ort.SessionOptions:
    """Explicit options so a model runs the same everywhere: full graph optimisation, sequential
    execution (the graphs are chains; parallel branches would only fight for two cores), worker
    threads that sleep rather than spin when idle (``spin_wait``: ONNX Runtime's default, for a
    benchmark to compare), quiet logs."""
    opts = ort.SessionOptions()
    if intra_op_threads is not None:
        if not isinstance(intra_op_threads, int) or intra_op_threads < 1:
            raise ValidationError(
                f"intra_op_threads: expected a positive integer or None, got {intra_op_threads!r}"
            )
        opts.intra_op_num_threads = intra_op_threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # ORT's worker threads spin-wait between ops by default, holding a core that the live rig's
    # source, outputs and Python code need: on 2 cores that cost the shipped model a third of its
    # unpaced rate and made the paper's network drop frames of a 10 Hz camera; offline, with the
    # cores otherwise idle, it gained nothing (docs/model.md, "int8 backbones", has the figures
    # and the commands: benchmarks/bench_rig.py --ort-spinning).
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin_wait else "0")
    # errors only: ORT's warnings about unused initializers are noise here
    opts.log_severity_level = 3
    return opts


class OnnxModel:
    """A loaded, checked model folder. Build with :meth:`load`."""

    def __init__(
        self,
        model_dir: Path,
        contract: ModelContract,
        model_id: str,
        backbone: ort.InferenceSession,
        aggregator: ort.InferenceSession,
    ) -> None:
        self.model_dir = model_dir
        self.contract = contract
        self.model_id = model_id
        self._backbone = backbone
        self._aggregator = aggregator
        # (x * scale - mean) / std as one multiply-add per channel; the same function feeds
        # training, so the two cannot drift apart. Crops arrive BGR, as OpenCV and Frame keep them.
        swap, gain, offset = input_affine(contract.input_norm)
        self._swap_rb = swap
        self._norm_gain = np.asarray(gain, dtype=np.float32)
        self._norm_offset = np.asarray(offset, dtype=np.float32)

    def __repr__(self) -> str:
        c = self.contract
        return (
            f"OnnxModel({str(self.model_dir)!r}, id={self.model_id}, crop={c.crop_size_px}px, "
            f"D={c.embedding_dim}, window={c.frames_per_window}x{c.crops_per_frame})"
        )

    @classmethod
    def load(
        cls,
        model_dir: str | os.PathLike,
        *,
        intra_op_threads: int | None = None,
        spin_wait: bool = False,
        expect: Mapping[str, Any] | None = None,
    ) -> OnnxModel:
        """Open ``model_dir`` and check both graphs against their contract.

        ``spin_wait``: ONNX Runtime's worker threads spin between ops, its default and not the
        rig's (:func:`session_options`). ``expect`` optionally names contract fields the caller relies on, e.g.
        ``{"crops_per_frame": 4}``; a model that differs is refused (see :func:`check_expected`).
        Raises :class:`ModelError` for an unusable folder and :class:`ContractMismatch` for a
        model that does not fit.
        """
        root = Path(model_dir)
        from estimator.models import is_shipped

        shipped = is_shipped(root)
        try:
            return cls._load(root, intra_op_threads=intra_op_threads, spin_wait=spin_wait, expect=expect,
                             checksums_required=shipped)
        except ModelError as exc:
            if not shipped or isinstance(exc, ContractMismatch) and expect:
                raise  # a user's folder; or a caller's expectation the shipped model does not meet
            # The remedy a user's folder gets (copy it again, re-export it) is not one for the
            # package's own files: what is wrong, and to reinstall.
            what = str(exc).split("; ", 1)[0]
            raise type(exc)(f"the model installed with sunrig is damaged: {what}; {REINSTALL}") from None

    @classmethod
    def _load(cls, root: Path, *, intra_op_threads: int | None, spin_wait: bool, expect: Mapping[str, Any] | None,
              checksums_required: bool) -> OnnxModel:
        if not root.is_dir():
            what = "is a file, not a model folder" if root.exists() else "does not exist"
            raise ModelError(
                f"model folder {str(root)!r} {what}; "
                f"pass the folder that holds {BACKBONE_FILE} and {AGGREGATOR_FILE}"
            )
        paths = {name: root / name for name in (BACKBONE_FILE, AGGREGATOR_FILE)}
        missing = [name for name, p in paths.items() if not p.is_file()]
        if missing:
            if (root / CHECKPOINT).is_file():
                raise ModelError(f"{root} holds a training run that has not exported its model yet; export it as it "
                                 f"stands with `sunrig train --out {root} --export-only DIR` and pass --model DIR, "
                                 "or run its `sunrig train` command again to finish and export it")
            raise ModelError(
                f"model folder {str(root)!r} lacks {' and '.join(missing)}; a model folder holds "
                f"{BACKBONE_FILE} and {AGGREGATOR_FILE} as written by `sunrig train`"
            )
        opts = session_options(intra_op_threads, spin_wait=spin_wait)
        blobs = {name: _read_graph(p) for name, p in paths.items()}
        digests = {name: hashlib.sha256(blob).hexdigest() for name, blob in blobs.items()}
        _check_checksums(root, digests, required=checksums_required)
        sessions = {name: _open_session(paths[name], blobs[name], opts) for name in paths}
        contracts = {
            name: _read_contract(paths[name], sessions[name], ROLES[name]) for name in paths
        }
        bb, agg = contracts[BACKBONE_FILE], contracts[AGGREGATOR_FILE]
        diff = bb.differences(agg)
        if diff:
            # A field such as `training` holds a whole recipe: name it, do not print both copies.
            shown = "; ".join(d if len(d) <= 100 else d.split(":", 1)[0] + ": differs" for d in diff)
            raise ContractMismatch(
                f"model folder {str(root)!r}: {BACKBONE_FILE} and {AGGREGATOR_FILE} carry "
                f"different contracts (backbone != aggregator: {shown}); "
                "both graphs must come from one export: copy the model folder again, or re-export it"
            )
        _check_io(paths[BACKBONE_FILE], sessions[BACKBONE_FILE], _BACKBONE_IO, bb)
        _check_io(paths[AGGREGATOR_FILE], sessions[AGGREGATOR_FILE], _AGGREGATOR_IO, bb)
        if expect:
            check_expected(bb, expect, where=f"model {str(root)!r}")
        digest = hashlib.sha256()
        for name in (BACKBONE_FILE, AGGREGATOR_FILE):
            digest.update(bytes.fromhex(digests[name]))
        return cls(
            root, bb, digest.hexdigest()[:12], sessions[BACKBONE_FILE], sessions[AGGREGATOR_FILE]
        )

    # ----------------------------------------------------------------------------------------

    def normalise(self, crops_bgr: np.ndarray) -> np.ndarray:
        """Crops [N, S, S, 3] uint8 BGR -> the backbone's input [N, 3, S, S] float32, normalised
        as ``contract.input_norm`` says."""
        s = self.contract.crop_size_px
        if not isinstance(crops_bgr, np.ndarray):
            raise ValidationError(
                f"crops_bgr: expected a numpy array, got {type(crops_bgr).__name__}"
            )
        if crops_bgr.dtype != np.uint8:
            raise ValidationError(f"crops_bgr: expected dtype uint8, got {crops_bgr.dtype}")
        if crops_bgr.ndim != 4 or crops_bgr.shape[1:] != (s, s, 3):
            raise ValidationError(
                f"crops_bgr: expected shape (N, {s}, {s}, 3) BGR, got {crops_bgr.shape}"
            )
        x = crops_bgr[..., ::-1] if self._swap_rb else crops_bgr
        x = x.astype(np.float32) * self._norm_gain + self._norm_offset
        return np.ascontiguousarray(x.transpose(0, 3, 1, 2))

    def embed(self, crops_bgr: np.ndarray, *, batch_size: int = DEFAULT_EMBED_BATCH) -> np.ndarray:
        """Backbone: crops [N, S, S, 3] uint8 BGR -> embeddings [N, D] float32, run
        ``batch_size`` crops at a time."""
        if not isinstance(batch_size, int) or batch_size < 1:
            raise ValidationError(f"batch_size: expected a positive integer, got {batch_size!r}")
        x = self.normalise(crops_bgr)
        d = self.contract.embedding_dim
        if len(x) == 0:
            return np.zeros((0, d), dtype=np.float32)
        parts = [
            self._backbone.run([BACKBONE_OUTPUT], {BACKBONE_INPUT: x[i : i + batch_size]})[0]
            for i in range(0, len(x), batch_size)
        ]
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return np.asarray(out, dtype=np.float32)

    def aggregate(self, embeddings: np.ndarray, angles: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Aggregator: embeddings [B, T, D], angles [B, T, 3] (yaw, horizontal, vertical; rad),
        mask [B, T] bool (True = real token) -> per-token sun vectors [B, T, 3] float32, each in
        its token's heading frame. Padded tokens come back as zeros."""
        d = self.contract.embedding_dim
        emb = _float32("embeddings", embeddings)
        ang = _float32("angles", angles)
        if emb.ndim != 3 or emb.shape[2] != d:
            raise ValidationError(f"embeddings: expected shape (B, T, {d}), got {emb.shape}")
        b, t = emb.shape[:2]
        if ang.shape != (b, t, 3):
            raise ValidationError(
                f"angles: expected shape ({b}, {t}, 3) to match the embeddings, got {ang.shape}"
            )
        m = np.asarray(mask)
        if m.dtype != np.bool_:
            raise ValidationError(f"mask: expected dtype bool (True = real token), got {m.dtype}")
        if m.shape != (b, t):
            raise ValidationError(f"mask: expected shape ({b}, {t}), got {m.shape}")
        if b == 0 or t == 0:
            return np.zeros((b, t, 3), dtype=np.float32)
        if not np.all(np.isfinite(ang)):
            raise ValidationError("angles: expected finite radians, got NaN or inf")
        feeds = {
            AGG_INPUT_EMBEDDINGS: np.ascontiguousarray(emb),
            AGG_INPUT_ANGLES: np.ascontiguousarray(ang),
            AGG_INPUT_MASK: np.ascontiguousarray(m),
        }
        return np.asarray(self._aggregator.run([AGG_OUTPUT], feeds)[0], dtype=np.float32)


def check_expected(
    contract: ModelContract, expect: Mapping[str, Any], where: str = "model"
) -> None:
    """Refuse a contract whose fields differ from ``expect`` (a subset of its fields).

    A dict value is compared key by key, so ``{"encoding": {"kind": "cyclic-nested-sine"}}``
    checks only the kind.
    """
    have = asdict(contract)
    unknown = sorted(set(expect) - set(have))
    if unknown:
        raise ValidationError(
            f"expect: not contract fields: {', '.join(unknown)}; known: {', '.join(sorted(have))}"
        )
    diff = []
    for key, want in expect.items():
        got = have[key]
        if isinstance(want, Mapping) and isinstance(got, Mapping):
            diff += [
                f"{key}.{k}: {got.get(k)!r} != expected {v!r}"
                for k, v in want.items()
                if got.get(k) != v
            ]
        elif got != want:
            diff.append(f"{key}: {got!r} != expected {want!r}")
    if diff:
        raise ContractMismatch(
            f"{where} does not fit this configuration ({'; '.join(diff)}); use a model made for it"
        )


# --------------------------------------------------------------------------------------------


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _float32(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValidationError(f"{name}: expected a float array, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)


def _read_graph(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: cannot read it ({exc.strerror or exc}); check its permissions, or copy the "
                         "model folder again") from None


def _check_checksums(root: Path, digests: Mapping[str, str], required: bool = False) -> None:
    """Compare the graphs with the folder's SHA256SUMS, when it has one (an export writes it).
    ``required``: a folder without one is refused (the shipped model, which always has one)."""
    path = root / CHECKSUMS_FILE
    if path.exists() and not path.is_file():  # a folder of that name: not a sums file to skip quietly
        raise ModelError(f"{path} is not a file; copy the model folder again, re-export it, or remove "
                         f"{CHECKSUMS_FILE} to load it unchecked")
    if not path.is_file():
        if required:
            raise ModelError(f"{path} is missing; the graphs cannot be checked")
        return
    try:
        expected = parse_checksums(path.read_text(encoding="utf-8", errors="replace"))
    except OSError as exc:
        raise ModelError(f"{path}: cannot read it ({exc.strerror}); copy the model folder again") from None
    if not expected:
        raise ModelError(f"{path}: no line in sha256sum's format (HEX  NAME); copy the model folder again, "
                         f"re-export it, or delete {CHECKSUMS_FILE} to load it unchecked")
    unlisted = [name for name in digests if name not in expected]
    if unlisted:
        # An empty or garbled sums file must not pass for a checked folder.
        raise ModelError(f"{path}: no checksum for {' and '.join(unlisted)} (the file is damaged); copy the model "
                         f"folder again, re-export it, or delete {CHECKSUMS_FILE} to load it unchecked")
    damaged = [name for name, digest in digests.items() if expected[name] != digest]
    if damaged:
        verb = "does" if len(damaged) == 1 else "do"
        raise ModelError(f"model folder {str(root)!r}: {' and '.join(damaged)} {verb} not match {CHECKSUMS_FILE} "
                         "(damaged in a copy, or changed by hand); copy the model folder again, or re-export it "
                         "from its training run (sunrig train --out RUN --export-only DIR)")


def _open_session(path: Path, blob: bytes, opts: ort.SessionOptions) -> ort.InferenceSession:
    try:
        # From bytes, not the path: the graph we hash for model_id is the graph we run.
        return ort.InferenceSession(blob, sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001 - ORT's pybind error classes differ across versions
        raise ModelError(
            f"{path}: not a usable ONNX graph ({type(exc).__name__}: {_one_line(exc)[:200]}); "
            "re-export the model with estimator.export.export_model"
        ) from None


def _read_contract(path: Path, session: ort.InferenceSession, role: str) -> ModelContract:
    meta = session.get_modelmeta().custom_metadata_map
    if METADATA_CONTRACT_KEY not in meta:
        raise ModelError(
            f"{path}: the graph carries no {METADATA_CONTRACT_KEY!r} metadata, "
            "so it was not exported by sunrig; "
            "export it with estimator.export.export_model"
        )
    got_role = meta.get(METADATA_GRAPH_KEY)
    if got_role != role:
        raise ContractMismatch(
            f"{path}: holds the {got_role!r} graph ({METADATA_GRAPH_KEY} metadata), "
            f"expected {role!r}; the files were renamed or swapped: "
            f"put the {role} graph in {path.name} or re-export the model"
        )
    text = meta[METADATA_CONTRACT_KEY]
    # Check the version first: a newer contract may differ in every other field, and saying
    # "version 2, this runtime reads 1" tells the user what to do, where a list of fields would not.
    try:
        version = json.loads(text).get("version")
    except (json.JSONDecodeError, AttributeError):
        version = CONTRACT_VERSION  # let from_json name the problem
    if version != CONTRACT_VERSION:
        newer = isinstance(version, int) and version > CONTRACT_VERSION
        fix = "upgrade sunrig to read it" if newer else "re-export the model with this sunrig"
        raise ContractMismatch(
            f"{path}: contract version {version!r}, "
            f"this runtime reads version {CONTRACT_VERSION}; {fix}"
        )
    return ModelContract.from_json(text, where=str(path))


def _check_io(
    path: Path, session: ort.InferenceSession, spec: dict, contract: ModelContract
) -> None:
    """Compare the graph's declared inputs and outputs with the contract's names and sizes."""
    sizes = {"S": contract.crop_size_px, "D": contract.embedding_dim}
    labels = {"S": "crop_size_px", "D": "embedding_dim"}
    # An input the contract does not name would be missing from every feed, and the model would
    # load and then fail on the first frame. (ONNX Runtime lists an input that has a default value
    # among the overridable initializers, not here: it needs no feed.)
    unknown = sorted({a.name for a in session.get_inputs()} - set(spec["inputs"]))
    if unknown:
        raise ContractMismatch(
            f"{path}: input(s) {unknown} that no sunrig runtime feeds (it feeds {sorted(spec['inputs'])}); "
            "re-export the model"
        )
    for kind, args in (("inputs", session.get_inputs()), ("outputs", session.get_outputs())):
        declared = {a.name: a for a in args}
        for name, (dtype, shape) in spec[kind].items():
            arg = declared.get(name)
            if arg is None:
                raise ContractMismatch(
                    f"{path}: no {kind[:-1]} named {name!r} (has {sorted(declared)}); "
                    "re-export the model"
                )
            if arg.type != dtype:
                raise ContractMismatch(
                    f"{path}: {kind[:-1]} {name!r} is {arg.type}, expected {dtype}; "
                    "re-export the model"
                )
            got = list(arg.shape)
            if len(got) != len(shape):
                raise ContractMismatch(
                    f"{path}: {kind[:-1]} {name!r} has shape {got}, "
                    f"expected rank {len(shape)}; re-export the model"
                )
            for axis, (g, want) in enumerate(zip(got, shape, strict=True)):
                value = sizes.get(want, want) if isinstance(want, str) else want
                if value is None or not isinstance(g, int):
                    continue  # a free axis, or one the graph leaves symbolic
                if g != value:
                    field = (
                        f"contract {labels[want]} {value}"
                        if isinstance(want, str)
                        else f"expected {value}"
                    )
                    raise ContractMismatch(
                        f"{path}: {kind[:-1]} {name!r} axis {axis} is {g} but {field}; "
                        "the graph and its contract disagree: re-export the model"
                    )
