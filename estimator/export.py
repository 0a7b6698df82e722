"""Export the torch modules to a model folder: ``backbone.onnx`` + ``aggregator.onnx``, each
carrying the contract in its ONNX metadata. Train extra only (torch, onnx, onnxscript).

The exporter is torch's ``dynamo=True`` one (torch.export + onnxscript): it is the default and the
supported path since torch 2.9, while the TorchScript exporter is deprecated and warns on every
call. ``exporter="legacy"`` stays available as a fallback for a graph dynamo cannot trace; both
give the same inputs, outputs, dynamic axes and metadata, and the runtime cannot tell them apart.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import tempfile
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from estimator.contract import (
    AGG_INPUT_ANGLES,
    AGG_INPUT_EMBEDDINGS,
    AGG_INPUT_MASK,
    AGG_OUTPUT,
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    BACKBONE_INPUT,
    BACKBONE_OUTPUT,
    CHECKSUMS_FILE,
    METADATA_CONTRACT_KEY,
    METADATA_GRAPH_KEY,
    PAPER_CROPS_PER_FRAME,
    ModelContract,
    format_checksums,
    set_metadata,
)
from estimator.nets import TINY, Aggregator, Backbone, NetConfig
from rig.errors import MissingExtraError, ModelError, ValidationError, require_torch
from rig.files import make_output_folder, sync_to_disk

require_torch()  # a missing torch names the extra to install
import torch  # noqa: E402  (imported, not require_torch's value, so mypy knows torch.nn.Module)

try:
    import onnx
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise MissingExtraError(
        "exporting needs onnx: install the train extra with `pip install 'sunrig[train]'`"
    ) from exc

EXPORTERS = ("dynamo", "legacy")
# The hidden folder in the model folder where an export stages its files before they replace the
# model's: one left behind is an export killed midway (sunrig train removes them, holding its run).
STAGING_PREFIX = ".export-"
# Opset 18 is what the legacy exporter and onnxruntime >= 1.17 (our floor) both support fully;
# dynamo picks its own (>= 18) when given None.
LEGACY_OPSET = 18

# Example sizes for tracing. Dynamic axes need examples >= 2: torch.export specialises an axis
# that is 0 or 1 in the example to a constant.
_EXAMPLE_N = 2
_EXAMPLE_B, _EXAMPLE_T = 2, 5


def export_model(
    backbone: Backbone,
    aggregator: Aggregator,
    contract: ModelContract,
    out_dir: str | os.PathLike,
    *,
    exporter: str = "dynamo",
) -> Path:
    """Write ``backbone.onnx`` and ``aggregator.onnx`` for ``contract`` into ``out_dir``.

    Both graphs are traced in eval mode (dropout off, batch-norm statistics frozen); the modules'
    own training flags are restored afterwards. Each file is checked with ``onnx.checker`` and moved
    into place only when complete and on the disk, so a failed export (or a power loss)
    never leaves a half-valid folder behind.
    """
    _check_against_contract(backbone, aggregator, contract)
    out = make_output_folder(out_dir, what="model folder", holds="a model is a folder")
    s = contract.crop_size_px
    gen = torch.Generator().manual_seed(0)
    crops = torch.randn(_EXAMPLE_N, 3, s, s, generator=gen)
    embeddings = torch.randn(_EXAMPLE_B, _EXAMPLE_T, contract.embedding_dim, generator=gen)
    angles = torch.rand(_EXAMPLE_B, _EXAMPLE_T, 3, generator=gen) * 2.0 * math.pi - math.pi
    mask = torch.ones(_EXAMPLE_B, _EXAMPLE_T, dtype=torch.bool)
    mask[1, 3:] = False
    with (
        _eval_mode(backbone, aggregator),
        tempfile.TemporaryDirectory(dir=out, prefix=STAGING_PREFIX) as tmp,
    ):
        staged = {
            BACKBONE_FILE: export_graph(
                backbone,
                (crops,),
                Path(tmp) / BACKBONE_FILE,
                input_names=[BACKBONE_INPUT],
                output_names=[BACKBONE_OUTPUT],
                dynamic_axes={BACKBONE_INPUT: {0: "N"}, BACKBONE_OUTPUT: {0: "N"}},
                exporter=exporter,
                metadata={
                    METADATA_CONTRACT_KEY: contract.to_json(),
                    METADATA_GRAPH_KEY: "backbone",
                },
            ),
            AGGREGATOR_FILE: export_graph(
                aggregator,
                (embeddings, angles, mask),
                Path(tmp) / AGGREGATOR_FILE,
                input_names=[AGG_INPUT_EMBEDDINGS, AGG_INPUT_ANGLES, AGG_INPUT_MASK],
                output_names=[AGG_OUTPUT],
                dynamic_axes={
                    name: {0: "B", 1: "T"}
                    for name in (AGG_INPUT_EMBEDDINGS, AGG_INPUT_ANGLES, AGG_INPUT_MASK, AGG_OUTPUT)
                },
                exporter=exporter,
                metadata={
                    METADATA_CONTRACT_KEY: contract.to_json(),
                    METADATA_GRAPH_KEY: "aggregator",
                },
            ),
        }
        digests = {name: hashlib.sha256(path.read_bytes()).hexdigest() for name, path in staged.items()}
        # The sums first: a folder caught between the two steps fails its check loudly rather
        # than passing with stale graphs.
        sums = Path(tmp) / CHECKSUMS_FILE
        sums.write_text(format_checksums(digests), encoding="utf-8")
        # Each file on the disk before it replaces the old one, and the renames after: renamed with
        # their data still in memory, a power loss could leave empty graphs and the old ones gone.
        for path in (sums, *staged.values()):
            sync_to_disk(path)
        os.replace(sums, out / CHECKSUMS_FILE)
        for name, path in staged.items():
            os.replace(path, out / name)
        sync_to_disk(out)
    return out


def export_graph(
    module: torch.nn.Module,
    args: tuple[Any, ...],
    path: str | os.PathLike,
    *,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Mapping[int, str]],
    exporter: str = "dynamo",
    metadata: Mapping[str, str] | None = None,
) -> Path:
    """Export one module to a single self-contained ONNX file, add ``metadata`` and check it.

    ``dynamic_axes`` maps input and output names to ``{axis: symbol}``; inputs sharing a symbol
    share the dimension. The module is traced in whatever mode it is in: callers set eval mode.
    """
    if exporter not in EXPORTERS:
        raise ValidationError(f"exporter: expected one of {EXPORTERS}, got {exporter!r}")
    path = Path(path)
    with _quiet_exporter():
        if exporter == "dynamo":
            dims: dict[str, Any] = {}
            shapes = tuple(
                {
                    axis: dims.setdefault(sym, torch.export.Dim(sym))
                    for axis, sym in dynamic_axes.get(name, {}).items()
                }
                or None
                for name in input_names
            )
            torch.onnx.export(
                module,
                args,
                str(path),
                input_names=list(input_names),
                output_names=list(output_names),
                dynamo=True,
                external_data=False,
                dynamic_shapes=shapes,
                verbose=False,
            )
        else:
            torch.onnx.export(
                module,
                args,
                str(path),
                input_names=list(input_names),
                output_names=list(output_names),
                dynamo=False,
                dynamic_axes={k: dict(v) for k, v in dynamic_axes.items()},
                opset_version=LEGACY_OPSET,
            )
    model = onnx.load(str(path))
    got_in = [i.name for i in model.graph.input]
    got_out = [o.name for o in model.graph.output]
    if got_in != list(input_names) or got_out != list(output_names):
        raise ModelError(
            f"{path.name}: the exporter named the graph's inputs {got_in} and outputs {got_out}, "
            f"expected {list(input_names)} and {list(output_names)}; try exporter='legacy'"
        )
    set_metadata(model, dict(metadata or {}))
    onnx.checker.check_model(model, full_check=True)
    # save_as_external_data=False: one file per graph, so a model folder is just two files.
    onnx.save_model(model, str(path), save_as_external_data=False)
    return path


def build_random_nets(config: NetConfig, seed: int) -> tuple[Backbone, Aggregator]:
    """Untrained modules in eval mode with reproducible, deliberately non-trivial weights.

    Fresh batch norms are identity maps (mean 0, var 1, weight 1, bias 0) and fresh layer norms
    have unit gain, which would hide an export that drops or misfolds them; both get random
    statistics and affine parameters here.
    """
    backbone, aggregator = config.build(seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        for m in (*backbone.modules(), *aggregator.modules()):
            # (None only with track_running_stats=False, which the nets do not use: nothing to set.)
            if isinstance(m, torch.nn.BatchNorm2d) and m.running_mean is not None and m.running_var is not None:
                m.running_mean.copy_(0.1 * torch.randn(m.num_features, generator=gen))
                m.running_var.copy_(0.5 + torch.rand(m.num_features, generator=gen))
            if isinstance(m, torch.nn.BatchNorm2d | torch.nn.LayerNorm):
                m.weight.copy_(0.5 + torch.rand(m.weight.shape, generator=gen))
                m.bias.copy_(0.1 * torch.randn(m.bias.shape, generator=gen))
    return backbone.eval(), aggregator.eval()


def build_random_model(
    out_dir: str | os.PathLike,
    config: NetConfig = TINY,
    *,
    seed: int = 0,
    crops_per_frame: int = PAPER_CROPS_PER_FRAME,
    frames_per_window: int = 8,
    exporter: str = "dynamo",
) -> Path:
    """Export an UNTRAINED model (random weights) for tests: a real folder, meaningless answers.

    ``config`` is any architecture (default: the ``tiny`` preset, whose export takes seconds).
    The contract says so (``training.trained`` is False) and records the seed, so
    ``build_random_nets(NetConfig.from_architecture(contract.architecture), seed)`` rebuilds the
    exact torch modules behind the folder.
    """
    backbone, aggregator = build_random_nets(config, seed)
    contract = config.contract(
        crops_per_frame=crops_per_frame,
        frames_per_window=frames_per_window,
        training={"trained": False, "seed": seed, "note": "random weights, for tests only"},
    )
    return export_model(backbone, aggregator, contract, out_dir, exporter=exporter)


def _check_against_contract(
    backbone: Backbone, aggregator: Aggregator, contract: ModelContract
) -> None:
    """Refuse to write a contract the graphs would not keep."""
    problems = []
    if backbone.embedding_dim != contract.embedding_dim:
        problems.append(
            f"backbone embedding_dim {backbone.embedding_dim} != contract {contract.embedding_dim}"
        )
    if aggregator.embedding_dim != contract.embedding_dim:
        problems.append(
            f"aggregator embedding_dim {aggregator.embedding_dim} "
            f"!= contract {contract.embedding_dim}"
        )
    enc = aggregator.encoding.params()
    for key, value in enc.items():
        want = contract.encoding.get(key)
        same = (
            math.isclose(value, want)
            if isinstance(value, float) and isinstance(want, int | float)
            else value == want
        )
        if not same:
            problems.append(f"encoding.{key}: aggregator {value!r} != contract {want!r}")
    if problems:
        raise ValidationError(
            "export_model: the modules do not fit the contract: " + "; ".join(problems)
        )


@contextlib.contextmanager
def _eval_mode(*modules: torch.nn.Module) -> Iterator[None]:
    flags = [m.training for m in modules]
    try:
        for m in modules:
            m.eval()
        with torch.no_grad():
            yield
    finally:
        for m, flag in zip(modules, flags, strict=True):
            m.train(flag)


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence exporter chatter that is not about our model (missing torchvision ops, torch
    internals' deprecations, shared axis names), keeping every other warning."""
    logger = logging.getLogger("torch.onnx._internal.exporter._registration")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\).*")
            warnings.filterwarnings("ignore", message=r".*The axis name: .* will not be used.*")
            # The legacy exporter warns that it is deprecated, once per call and per helper;
            # choosing it is deliberate.
            warnings.filterwarnings("ignore", message=r".*legacy TorchScript-based ONNX export.*")
            warnings.filterwarnings(
                "ignore", category=DeprecationWarning, module=r"torch\.onnx\..*"
            )
            yield
    finally:
        logger.setLevel(level)
