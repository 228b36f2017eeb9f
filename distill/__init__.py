"""Predictors phi(window) -> next xy: the interface, constant velocity, the ReLU social teacher and the certified GELU student."""
