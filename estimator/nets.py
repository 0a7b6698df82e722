"""The paper's network in PyTorch: ResNet18-style backbone, cyclic positional encoding, and the
transformer aggregator (Lee et al., IJCV 2023, Sec. 3), plus the training loss.

Train extra only: nothing under ``estimator`` imports this module at package import time, and the
runtime reads the exported ONNX graphs with onnxruntime alone. Every op here is chosen so the
export is plain ONNX (Conv, MatMul, Softmax, LayerNormalization, Sin, Cos, Where): attention is
written out by hand rather than through ``nn.MultiheadAttention`` or fused SDPA kernels.

Frames follow ``rig.geometry``: per-token outputs live in that token's heading frame (x right,
y forward, z up); :func:`world_from_heading_torch` rotates them into ENU by the frame's yaw.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from estimator.contract import PAPER_CROP_FOV_DEG, PAPER_CROPS_PER_FRAME, YAW_INPUT, ModelContract
from rig.errors import ValidationError, require_torch

# Imported after the check, not through its return value: mypy needs real imports to type the
# nn.Module subclasses and Tensor annotations below.
require_torch()  # a missing torch names the extra to install
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import Tensor, nn  # noqa: E402

ENCODING_KIND = "cyclic-nested-sine"

# Added to attention scores of padded keys. Large enough that exp() underflows to exactly 0 in
# float32 next to any real score, finite so a row whose keys are all padding gives a uniform
# softmax instead of NaN (-inf - -inf).
MASK_NEGATIVE = -1.0e9

# An ONNX file is one protobuf message, which cannot pass 2 GiB, and export writes each graph whole
# into one file, its weights inside (estimator/export.py: a model folder is its two graphs).
ONNX_FILE_MAX_BYTES = 2**31 - 1
# What a graph holds beyond its float32 weights (nodes, names, shapes, the contract), per
# transformer layer and once more for the rest of the aggregator: the tiny preset's graph grows by
# 96.9 kB a layer for 63.4 kB of weights, and with one layer holds 60 kB beside its 76.9 kB of
# weights; rounded up, so that an estimate from it is an upper bound.
ONNX_BYTES_PER_LAYER = 40_000

# Below this norm a predicted vector has no direction; the cosine term uses it as a floor so a
# zero prediction gives a finite loss and gradient instead of 0/0.
_NORM_EPS = 1.0e-6


def default_depth_per_angle(width: int) -> int:
    """The largest even depth whose three stacked encodings fit in ``width`` (170 for 512)."""
    return 2 * (width // 6)


# --------------------------------------------------------------------------------------------
# Positional encoding


class CyclicPositionalEncoding(nn.Module):
    """Eq. (posenc): for each angle phi and i in [0, d/2),

    PE(phi, 2i)     = sin(sin(phi) * alpha / base^(2i/d)),
    PE(phi, 2i + 1) = sin(cos(phi) * alpha / base^(2i/d)).

    The inner sin/cos make it periodic in 2 pi; interlacing the two makes it unique per angle.
    The three angles (yaw, horizontal, vertical view angle; radians) are encoded alike, stacked
    to 3d values and zero-padded to ``width`` so the result can be added to a token.
    ``depth_per_angle`` None means the largest even d that fits: 2 floor(width / 6).
    """

    freq: Tensor  # [d/2] buffer (register_buffer in __init__), declared so it types as a Tensor

    def __init__(self, alpha: float, base: float, depth_per_angle: int | None, width: int) -> None:
        super().__init__()
        if depth_per_angle is None:
            depth_per_angle = default_depth_per_angle(width)
        if not (
            isinstance(depth_per_angle, int) and depth_per_angle > 0 and depth_per_angle % 2 == 0
        ):
            raise ValidationError(
                f"depth_per_angle: expected a positive even integer, got {depth_per_angle!r}"
            )
        if 3 * depth_per_angle > width:
            raise ValidationError(
                f"depth_per_angle: 3 x {depth_per_angle} encoding values do not fit "
                f"a width of {width}; "
                f"use at most {default_depth_per_angle(width)}"
            )
        if not (math.isfinite(alpha) and alpha > 0 and math.isfinite(base) and base > 1):
            raise ValidationError(
                f"encoding: expected alpha > 0 and base > 1, got alpha={alpha}, base={base}"
            )
        self.alpha = float(alpha)
        self.base = float(base)
        self.depth_per_angle = depth_per_angle
        self.width = width
        i = torch.arange(depth_per_angle // 2, dtype=torch.float64)
        # Computed in float64 so the constants match the paper's formula to float32 precision.
        freq = self.alpha / self.base ** (2.0 * i / depth_per_angle)
        self.register_buffer("freq", freq.to(torch.float32), persistent=False)

    def params(self) -> dict[str, Any]:
        """The contract's ``encoding`` entry for this module."""
        return {
            "kind": ENCODING_KIND,
            "alpha": self.alpha,
            "base": self.base,
            "depth_per_angle": self.depth_per_angle,
        }

    def forward(self, angles: Tensor) -> Tensor:
        """angles [..., 3] (radians) -> [..., width]."""
        s = torch.sin(angles).unsqueeze(-1) * self.freq  # [..., 3, d/2]
        c = torch.cos(angles).unsqueeze(-1) * self.freq
        # stack on a new last axis then flatten: index 2i is the sin branch, 2i + 1 the cos branch.
        pe = torch.stack((torch.sin(s), torch.sin(c)), dim=-1).flatten(-3)  # [..., 3d]
        pad = self.width - 3 * self.depth_per_angle
        return F.pad(pe, (0, pad)) if pad else pe


# --------------------------------------------------------------------------------------------
# Backbone


class BasicBlock(nn.Module):
    """ResNet's two-conv residual block; attribute names follow torchvision so its ResNet18
    weights load by name when ``base_width`` is 64."""

    def __init__(self, in_ch: int, out_ch: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, stride=1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_ch)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Backbone(nn.Module):
    """ResNet18-style encoder: crops [N, 3, S, S] (normalised float) -> embeddings [N, D].

    Stages of ``blocks`` BasicBlocks with ``base_width * 2**k`` channels and a global average pool;
    D = 8 * base_width for the four ResNet18 stages. No classifier head.
    """

    def __init__(self, base_width: int = 64, blocks: tuple[int, ...] = (2, 2, 2, 2)) -> None:
        super().__init__()
        if not (isinstance(base_width, int) and base_width > 0):
            raise ValidationError(f"base_width: expected a positive integer, got {base_width!r}")
        if not blocks or any(int(b) < 1 for b in blocks):
            raise ValidationError(
                f"blocks: expected at least one stage of >= 1 block, got {blocks!r}"
            )
        self.base_width = base_width
        self.blocks = tuple(int(b) for b in blocks)
        self.conv1 = nn.Conv2d(3, base_width, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(base_width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        in_ch = base_width
        for k, n in enumerate(self.blocks):
            out_ch = base_width * 2**k
            stage = [BasicBlock(in_ch, out_ch, 1 if k == 0 else 2)]
            stage += [BasicBlock(out_ch, out_ch, 1) for _ in range(n - 1)]
            self.add_module(f"layer{k + 1}", nn.Sequential(*stage))
            in_ch = out_ch
        self.embedding_dim = in_ch
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, crops: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(crops))))
        for k in range(len(self.blocks)):
            x = getattr(self, f"layer{k + 1}")(x)
        # mean over H, W rather than AdaptiveAvgPool2d: one ReduceMean, any crop size.
        return x.mean(dim=(2, 3))


# --------------------------------------------------------------------------------------------
# Aggregator


class _SelfAttention(nn.Module):
    def __init__(self, width: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.head_dim = width // heads
        self.scale = 1.0 / math.sqrt(self.head_dim)
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)
        self.attn_drop = nn.Dropout(dropout)

    def forward(self, x: Tensor, key_bias: Tensor) -> Tensor:
        """x [B, T, W]; key_bias [B, 1, 1, T], 0 for real keys and MASK_NEGATIVE for padding."""
        qkv = self.qkv(x).unflatten(-1, (3, self.heads, self.head_dim))  # [B, T, 3, H, hd]
        q, k, v = (qkv.select(2, j).transpose(1, 2) for j in range(3))  # [B, H, T, hd]
        scores = torch.matmul(q, k.transpose(-2, -1)) * self.scale + key_bias
        attn = self.attn_drop(torch.softmax(scores, dim=-1))
        out = torch.matmul(attn, v).transpose(1, 2).flatten(2)  # [B, T, W]
        return self.proj(out)


class _EncoderLayer(nn.Module):
    """Pre-norm transformer layer as in ViT: x + attn(LN(x)), then x + MLP(LN(x))."""

    def __init__(self, width: int, heads: int, mlp: int, dropout: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(width)
        self.attn = _SelfAttention(width, heads, dropout)
        self.drop1 = nn.Dropout(dropout)
        self.norm2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(
            nn.Linear(width, mlp),
            nn.GELU(),
            nn.Dropout(dropout),
            nn.Linear(mlp, width),
            nn.Dropout(dropout),
        )

    def forward(self, x: Tensor, key_bias: Tensor) -> Tensor:
        x = x + self.drop1(self.attn(self.norm1(x), key_bias))
        return x + self.mlp(self.norm2(x))


class Aggregator(nn.Module):
    """ViT-style hybrid over a window of crop tokens (Sec. 3.2-3.3).

    forward(embeddings [B, T, D], angles [B, T, 3], mask [B, T] bool) -> [B, T, 3]: per-token sun
    vectors, each in its own token's heading frame. ``mask`` is True for real tokens; padded
    tokens are never attended to, so they cannot change real tokens' outputs, and their own
    outputs are zero.
    """

    def __init__(
        self,
        embedding_dim: int,
        width: int = 512,
        layers: int = 4,
        heads: int = 4,
        mlp: int = 1024,
        dropout: float = 0.2,
        alpha: float = 32.0,
        base: float = 10000.0,
        depth_per_angle: int | None = None,
    ) -> None:
        super().__init__()
        for name, v in (
            ("embedding_dim", embedding_dim),
            ("width", width),
            ("layers", layers),
            ("heads", heads),
            ("mlp", mlp),
        ):
            if not (isinstance(v, int) and v > 0):
                raise ValidationError(f"Aggregator.{name}: expected a positive integer, got {v!r}")
        if width % heads:
            raise ValidationError(f"Aggregator: width {width} is not divisible by {heads} heads")
        if not 0.0 <= dropout < 1.0:
            raise ValidationError(f"Aggregator.dropout: expected within [0, 1), got {dropout}")
        self.embedding_dim = embedding_dim
        self.width = width
        depth = default_depth_per_angle(width) if depth_per_angle is None else depth_per_angle
        self.embed = nn.Linear(embedding_dim, width)
        self.encoding = CyclicPositionalEncoding(alpha, base, depth, width)
        self.drop = nn.Dropout(dropout)
        self.layers = nn.ModuleList(
            _EncoderLayer(width, heads, mlp, dropout) for _ in range(layers)
        )
        self.norm = nn.LayerNorm(width)
        self.head = nn.Linear(width, 3)

    def forward(self, embeddings: Tensor, angles: Tensor, mask: Tensor) -> Tensor:
        x = self.drop(self.embed(embeddings) + self.encoding(angles))
        valid = mask.unsqueeze(-1)  # [B, T, 1]
        # [B, 1, 1, T]: broadcast over heads and queries, so only keys are masked.
        key_bias = torch.where(valid, 0.0, MASK_NEGATIVE).to(x.dtype).transpose(1, 2).unsqueeze(1)
        for layer in self.layers:
            x = layer(x, key_bias)
        out = self.head(self.norm(x))
        # Zero the padded tokens so a consumer that forgets the mask averages in nothing random.
        return torch.where(valid, out, torch.zeros_like(out))


# --------------------------------------------------------------------------------------------
# Loss and frames


def sun_loss(v_pred: Tensor, v_gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """The paper's L = (1 - v_gt . v_pred / |v_pred|) + (1 - |v_pred|)^2 + max(0, -z_pred).

    ``v_pred`` and ``v_gt`` are [..., 3] in the same frame, ``v_gt`` unit length; the result is the
    mean over vectors where ``mask`` (shape [...], True = valid) holds, or over all of them.
    """
    if v_pred.shape != v_gt.shape or v_pred.shape[-1] != 3:
        raise ValidationError(
            "sun_loss: expected matching shapes (..., 3), "
            f"got {tuple(v_pred.shape)} and {tuple(v_gt.shape)}"
        )
    norm = torch.linalg.vector_norm(v_pred, dim=-1)
    cosine = 1.0 - (v_gt * v_pred).sum(-1) / norm.clamp_min(_NORM_EPS)
    per_vector = cosine + (1.0 - norm) ** 2 + torch.relu(-v_pred[..., 2])
    return _masked_mean(per_vector, mask, "sun_loss")


def _masked_mean(per_vector: Tensor, mask: Tensor | None, name: str) -> Tensor:
    """The mean of a loss's per-vector terms where ``mask`` holds, or of all of them."""
    if mask is None:
        return per_vector.mean()
    if mask.shape != per_vector.shape:
        raise ValidationError(
            f"{name}: expected mask shape {tuple(per_vector.shape)}, got {tuple(mask.shape)}"
        )
    weights = mask.to(per_vector.dtype)
    # clamp: an all-padding batch gives 0 loss, not NaN.
    return (per_vector * weights).sum() / weights.sum().clamp_min(1.0)


def tail_loss(v_pred: Tensor, v_gt: Tensor, margin_rad: float, mask: Tensor | None = None) -> Tensor:
    """mean(max(0, angle(v_pred, v_gt) - margin)^2), the angle in radians, over the vectors where
    ``mask`` (shape [...], True = counted) holds, or all: nothing for an estimate within
    ``margin_rad`` of the truth, a pull that grows with the miss beyond it.

    Not in the paper. The paper's cosine term pulls on a miss by the sine of its angle, 0.57 at
    35 deg against 0.42 at 25 deg, and the worst windows are few among many; this term adds a
    pull on those only, of 2 (angle - margin) per unit of weight: 0.70 at 35 deg with a 15 deg
    margin. ``v_pred`` and ``v_gt`` are [..., 3] in the same frame.
    """
    if v_pred.shape != v_gt.shape or v_pred.shape[-1] != 3:
        raise ValidationError(
            "tail_loss: expected matching shapes (..., 3), "
            f"got {tuple(v_pred.shape)} and {tuple(v_gt.shape)}"
        )
    cosine = (v_gt * v_pred).sum(-1) / (
        torch.linalg.vector_norm(v_pred, dim=-1) * torch.linalg.vector_norm(v_gt, dim=-1)).clamp_min(_NORM_EPS)
    # Clamped inside (-1, 1): acos' slope is infinite at either end.
    angle = torch.acos(cosine.clamp(-1.0 + _NORM_EPS, 1.0 - _NORM_EPS))
    return _masked_mean(torch.relu(angle - margin_rad).square(), mask, "tail_loss")


def world_from_heading_torch(vectors: Tensor, yaw: Tensor) -> Tensor:
    """Rotate heading-frame vectors [..., 3] into ENU by yaw [...] (clockwise from north, rad).

    Same rotation as :func:`rig.geometry.world_from_heading` (the paper's R_f^-1): heading x
    (right) goes to (cos psi, -sin psi, 0), y (forward) to (sin psi, cos psi, 0), z stays up.
    """
    c, s = torch.cos(yaw), torch.sin(yaw)
    x, y, z = vectors.unbind(-1)
    return torch.stack((c * x + s * y, -s * x + c * y, z), dim=-1)


# --------------------------------------------------------------------------------------------
# Configurations


@dataclass(frozen=True)
class NetConfig:
    """Architecture of one model: what :meth:`build` makes and what the contract records."""

    base_width: int
    crop_size: int
    width: int = 512
    layers: int = 4
    heads: int = 4
    mlp: int = 1024
    dropout: float = 0.2
    alpha: float = 32.0
    base: float = 10000.0
    depth_per_angle: int | None = None
    blocks: tuple[int, ...] = (2, 2, 2, 2)

    def __post_init__(self) -> None:
        object.__setattr__(self, "blocks", tuple(int(b) for b in self.blocks))
        if self.depth_per_angle is None:
            object.__setattr__(self, "depth_per_angle", default_depth_per_angle(self.width))
        if not (isinstance(self.crop_size, int) and self.crop_size >= 16):
            raise ValidationError(
                f"NetConfig.crop_size: expected an integer >= 16 px, got {self.crop_size!r}"
            )

    @property
    def embedding_dim(self) -> int:
        return self.base_width * 2 ** (len(self.blocks) - 1)

    def encoding(self) -> dict[str, Any]:
        """The contract's ``encoding`` entry. ``yaw_input`` is how callers must form the yaw angle
        (relative to the window's newest frame); the graph itself encodes whatever yaw it is fed."""
        return {
            "kind": ENCODING_KIND,
            "alpha": self.alpha,
            "base": self.base,
            "depth_per_angle": self.depth_per_angle,
            "yaw_input": YAW_INPUT,
        }

    def architecture(self) -> dict[str, Any]:
        """JSON-native description for the contract (lists, not tuples, so it round-trips)."""
        arch = asdict(self)
        arch["blocks"] = list(self.blocks)
        return {"backbone": "resnet-basic", "aggregator": "vit-hybrid", **arch}

    @classmethod
    def from_architecture(cls, arch: dict[str, Any]) -> NetConfig:
        """Inverse of :meth:`architecture`, e.g. to rebuild the torch modules of a model folder."""
        names = {f.name for f in fields(cls)}
        kwargs = {k: v for k, v in arch.items() if k in names}
        if "blocks" in kwargs:
            kwargs["blocks"] = tuple(kwargs["blocks"])
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise ValidationError(f"architecture: cannot rebuild a NetConfig ({exc})") from None

    def sizes(self) -> tuple[int, int, int]:
        """Values (weights and buffers) of the backbone, of the aggregator apart from its
        transformer layers, and of one layer: what any depth takes, without building it."""
        backbone, aggregator = replace(self, layers=1).build()
        layer = _values(aggregator.layers[0])
        return _values(backbone), _values(aggregator) - layer, layer

    def aggregator_graph_bytes(self, layers: int) -> int:
        """An upper estimate of the exported aggregator graph's size with ``layers`` layers."""
        _, rest, layer = self.sizes()
        return 4 * (rest + layers * layer) + ONNX_BYTES_PER_LAYER * (layers + 1)

    def max_layers(self, sizes: tuple[int, int, int] | None = None) -> int:
        """The most transformer layers whose aggregator graph one ONNX file can hold: a deeper
        model would train for its hours and then fail to export. ``sizes``: :meth:`sizes`, if the
        caller has them (each call builds the networks)."""
        _, rest, layer = sizes or self.sizes()
        return (ONNX_FILE_MAX_BYTES - 4 * rest - ONNX_BYTES_PER_LAYER) // (4 * layer + ONNX_BYTES_PER_LAYER)

    def build(self, seed: int | None = None) -> tuple[Backbone, Aggregator]:
        """Fresh (untrained) modules; ``seed`` makes their initial weights reproducible."""
        if seed is not None:
            torch.manual_seed(seed)
        backbone = Backbone(self.base_width, self.blocks)
        aggregator = Aggregator(
            backbone.embedding_dim,
            self.width,
            self.layers,
            self.heads,
            self.mlp,
            self.dropout,
            self.alpha,
            self.base,
            self.depth_per_angle,
        )
        return backbone, aggregator

    def contract(
        self,
        *,
        crops_per_frame: int = PAPER_CROPS_PER_FRAME,
        frames_per_window: int = 8,
        crop_fov_deg: float | list[float] = PAPER_CROP_FOV_DEG,
        mirror_windows: bool = False,
        training: dict[str, Any] | None = None,
    ) -> ModelContract:
        return ModelContract(
            crop_size_px=self.crop_size,
            embedding_dim=self.embedding_dim,
            crop_fov_deg=crop_fov_deg,
            crops_per_frame=crops_per_frame,
            frames_per_window=frames_per_window,
            mirror_windows=mirror_windows,
            encoding=self.encoding(),
            architecture=self.architecture(),
            training=dict(training or {}),
        )


def _values(module: nn.Module) -> int:
    return sum(t.numel() for t in module.state_dict().values())


# Sec. 4.2: ResNet18 on 224 px crops; transformer of 4 layers, 4 heads, width 512, MLP 1024,
# dropout 0.2.
PAPER = NetConfig(base_width=64, crop_size=224, width=512, layers=4, heads=4, mlp=1024, dropout=0.2)
# Half-width ResNet18 on 128 px crops: ~10x the paper's training throughput on a CPU (DESIGN.md
# budget table), the same transformer.
LIGHT = NetConfig(base_width=32, crop_size=128, width=512, layers=4, heads=4, mlp=1024, dropout=0.2)
DEFAULT = LIGHT
# The default recipe for 90 minutes on 2 CPU cores: a quarter-width ResNet18 on 96 px crops
# (the paper's angular coverage per crop, ~4x LIGHT's training throughput) and a half-width
# transformer (4 layers, 4 heads, width 256, MLP 512): a width-512 transformer over 128-wide
# embeddings is 34 MB of fp32 weights, over the 30 MB a shipped model may take, for no gain.
FAST = NetConfig(base_width=16, crop_size=96, width=256, layers=4, heads=4, mlp=512, dropout=0.1)
# For tests and smoke runs of the training loop only: far too small to be a useful model.
TINY = NetConfig(base_width=8, crop_size=32, width=48, layers=1, heads=2, mlp=64, dropout=0.0)
PRESETS: dict[str, NetConfig] = {"paper": PAPER, "light": LIGHT, "fast": FAST, "tiny": TINY}
