"""Gradient surrogate (paper, Remark 3): a network that outputs the predictor's local input-Jacobian, exported to ONNX."""
