"""One table of numeric tolerances for the whole suite: change a number here, not in a test."""

import math

EXACT_F64 = 1e-12  # float64 identities (rotations, round trips of pure numpy code)
ANGLE_RAD_F64 = 1e-9  # angles recovered by float64 trigonometry
ONNX_VS_TORCH = 1e-4  # max abs difference between PyTorch and ONNX Runtime outputs (issue 2)
ENCODING_F32 = 2e-5  # float32 sin() of arguments up to alpha (32) carries ~32 x 6e-8 rad of rounding
BATCHED_F32 = 1e-5  # float32 batched vs one-by-one (summation order differs)
CALIBRATION_DEG = 1e-9  # the calibration is pure float64 rotation: exact up to rounding
JPEG_MEAN_ABS = 3.0  # mean absolute pixel difference after a JPEG round trip at quality 95
DEG = math.pi / 180.0
