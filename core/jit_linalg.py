"""Products of small dense matrices for the compiled core's kernels, written as loops: numba compiles them several times
faster than its BLAS-bound `@` (seconds per kernel on a fresh cache); at these sizes (tens of rows) a matrix-vector
product runs as fast, a matrix product about half as fast (the student's hot products keep `@`). Reassociation lets
the sums vectorise; NaN and inf still propagate (no fast-math beyond it), so a non-finite iterate is still seen."""
import numpy as np
from numba import njit


@njit(cache=True, fastmath={"reassoc", "contract"})
def matvec(M, x):
    """M x."""
    out = np.zeros(M.shape[0])
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            out[i] += M[i, j] * x[j]
    return out


@njit(cache=True, fastmath={"reassoc", "contract"})
def rmatvec(M, x):
    """M' x, row by row (contiguous)."""
    out = np.zeros(M.shape[1])
    for i in range(M.shape[0]):
        for j in range(M.shape[1]):
            out[j] += M[i, j] * x[i]
    return out


@njit(cache=True, fastmath={"reassoc", "contract"})
def matmul(A, B):
    """A B, as row updates out[i] += A[i, k] B[k] (contiguous, so the inner loop vectorises)."""
    out = np.zeros((A.shape[0], B.shape[1]))
    for i in range(A.shape[0]):
        row = out[i]
        for k in range(A.shape[1]):
            a, b = A[i, k], B[k]
            for j in range(len(row)):
                row[j] += a * b[j]
    return out
