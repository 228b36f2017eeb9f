"""ADMM-NNMPC (the paper's Algorithm 1) with OSQP sub-problems, swappable predictor gradients, the NNMPC baseline."""
