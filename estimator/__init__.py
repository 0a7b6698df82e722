"""The sun estimator: crops, the two ONNX graphs (backbone per frame, aggregator per window),
calibration into the world frame, and the aggregators. Runtime needs onnxruntime only; the torch
model definition and export live in :mod:`estimator.nets` and :mod:`estimator.export` (train extra).
"""
