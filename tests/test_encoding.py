"""The cyclic positional encoding (paper Eq. posenc): golden values from a plain-math reference,
in torch and in its ONNX export, and the two properties the paper asks of it: periodicity and
uniqueness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.tolerances import ENCODING_F32, ONNX_VS_TORCH

pytestmark = pytest.mark.torch
torch = pytest.importorskip("torch", reason="the torch model needs the train extra")

from estimator.nets import CyclicPositionalEncoding, default_depth_per_angle  # noqa: E402

ALPHA, BASE = 32.0, 10000.0
# Depth 8 x 3 angles = 24 values padded to 30, so the padding is exercised too.
SMALL = {"alpha": ALPHA, "base": BASE, "depth_per_angle": 8, "width": 30}
GOLDEN_ANGLES_RAD = [
    (0.0, 0.0, 0.0),
    (math.pi / 2, -0.3, 0.1),
    (math.radians(359.0), 0.25, -0.2),
    (-1.0, math.radians(-40.0), math.radians(14.5)),
    (3.0, math.pi, -math.pi / 2),
]


def golden_encoding(
    angles: tuple[float, float, float], alpha: float, base: float, d: int, width: int
) -> list[float]:
    """Eq. (posenc) written out with math.sin loops, independent of the module."""
    out: list[float] = []
    for phi in angles:
        for i in range(d // 2):
            f = alpha / base ** (2 * i / d)
            out.append(math.sin(math.sin(phi) * f))  # PE(phi, 2i)
            out.append(math.sin(math.cos(phi) * f))  # PE(phi, 2i + 1)
    return out + [0.0] * (width - len(out))


def encode(module: CyclicPositionalEncoding, angles) -> np.ndarray:
    with torch.no_grad():
        return module(torch.as_tensor(np.asarray(angles, dtype=np.float32))).numpy()


@pytest.fixture(scope="module")
def small() -> CyclicPositionalEncoding:
    return CyclicPositionalEncoding(**SMALL).eval()


@pytest.fixture(scope="module")
def onnx_small(small, tmp_path_factory):
    """The same encoding exported with the model exporter and run by onnxruntime."""
    ort = pytest.importorskip("onnxruntime")
    from estimator.export import export_graph

    path = export_graph(
        small,
        (torch.zeros(2, 3, 3),),
        tmp_path_factory.mktemp("encoding") / "encoding.onnx",
        input_names=["angles"],
        output_names=["encoding"],
        dynamic_axes={"angles": {0: "B", 1: "T"}, "encoding": {0: "B", 1: "T"}},
    )
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return lambda angles: session.run(None, {"angles": np.asarray(angles, dtype=np.float32)})[0]


def test_golden_values_torch(small):
    want = np.array([golden_encoding(a, ALPHA, BASE, 8, 30) for a in GOLDEN_ANGLES_RAD])
    got = encode(small, [GOLDEN_ANGLES_RAD])[0]
    assert got.shape == (len(GOLDEN_ANGLES_RAD), 30)
    np.testing.assert_allclose(got, want, atol=ENCODING_F32, rtol=0)
    assert np.all(got[:, 24:] == 0.0)


def test_golden_values_onnx(onnx_small, small):
    want = np.array([golden_encoding(a, ALPHA, BASE, 8, 30) for a in GOLDEN_ANGLES_RAD])
    got = onnx_small([GOLDEN_ANGLES_RAD])[0]
    np.testing.assert_allclose(got, want, atol=ENCODING_F32, rtol=0)
    # and the export matches torch on a batch of another shape than the one it was traced with
    rng = np.random.default_rng(1)
    batch = rng.uniform(-7.0, 7.0, size=(3, 11, 3))
    np.testing.assert_allclose(onnx_small(batch), encode(small, batch), atol=ONNX_VS_TORCH, rtol=0)


def test_paper_width_defaults_and_golden():
    d = default_depth_per_angle(512)
    assert d == 170 and CyclicPositionalEncoding(ALPHA, BASE, None, 512).depth_per_angle == 170
    module = CyclicPositionalEncoding(ALPHA, BASE, d, 512)
    angles = (0.7, -0.2, 0.05)
    np.testing.assert_allclose(
        encode(module, [angles])[0], golden_encoding(angles, ALPHA, BASE, d, 512), atol=ENCODING_F32
    )


def test_periodicity():
    module = CyclicPositionalEncoding(ALPHA, BASE, 170, 512)
    deg = [[math.radians(x)] * 3 for x in (0.0, 0.1, 359.9, 180.0)]
    e0, e01, e3599, e180 = encode(module, deg)
    wrap = np.linalg.norm(e3599 - e0)
    step = np.linalg.norm(e01 - e0)
    # 359.9 -> 0 deg is as smooth a step as 0 -> 0.1 deg, and far smaller than a half turn.
    assert wrap == pytest.approx(step, rel=1e-3)
    assert wrap < 0.05 * np.linalg.norm(e180 - e0)
    rng = np.random.default_rng(2)
    x = rng.uniform(-math.pi, math.pi, size=(64, 3))
    np.testing.assert_allclose(
        encode(module, x + 2 * math.pi), encode(module, x), atol=ENCODING_F32 * 2
    )
    np.testing.assert_allclose(
        encode(module, x - 4 * math.pi), encode(module, x), atol=ENCODING_F32 * 4
    )


def test_uniqueness_on_a_fine_grid():
    d = 170
    module = CyclicPositionalEncoding(ALPHA, BASE, d, 512)
    n = 3600  # 0.1 deg steps over [0, 2 pi)
    phi = np.arange(n) * (2 * math.pi / n)
    enc = torch.as_tensor(
        encode(module, np.stack([phi, 0 * phi, 0 * phi], -1))[:, :d], dtype=torch.float64
    )
    dist = torch.cdist(enc, enc)
    dist.fill_diagonal_(float("inf"))
    # Neighbours 0.1 deg apart are ~0.06-0.13 apart; anything near 0 would be a collision.
    assert dist.min().item() > 0.02
    idx = torch.arange(n)
    sep = (idx[:, None] - idx[None, :]).abs()
    sep = torch.minimum(sep, n - sep)
    # Angles 10 deg or more apart never come close: no folding of the encoding onto itself.
    assert dist[sep >= 100].min().item() > 1.0


def test_rejects_bad_parameters():
    from rig.errors import ValidationError

    with pytest.raises(ValidationError, match="even"):
        CyclicPositionalEncoding(ALPHA, BASE, 7, 30)
    with pytest.raises(ValidationError, match="do not fit"):
        CyclicPositionalEncoding(ALPHA, BASE, 12, 30)
