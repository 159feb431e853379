"""Small matrix products and solves that give the same bits on every CPU: the data-generation path.

``torch.matmul`` and ``torch.linalg.solve`` on the CPU call MKL, which picks its kernels by processor: an Intel Xeon
with AVX-512 and an AMD EPYC run different code paths and round differently in the last bit (measured: the
end-effector goal poses of EnvSpheres3D-RobotPanda-small differ by 2e-16 between the two, and the IK solutions of
EnvWarehouse's pose-region contexts by 8e-15, after which RRTConnect plans other paths). A dataset is identified by
its content, so the arithmetic that makes it must not depend on the processor. Here every product is written out as
elementwise multiplies and adds in a fixed order (the torch elementwise kernels are the same on every x86-64
processor with the same vector extension), and the 6 x 6 damped least-squares system of the IK is solved by a
Cholesky factorisation written the same way. torch's ``sin``, ``cos`` and even ``sqrt`` on the CPU call MKL's vector
maths library, whose results also depend on the processor (checked with ``MKL_CBWR=COMPATIBLE``, MKL's portable code
path, against its default one on an Intel Xeon: different bits for all three); :func:`sin`, :func:`cos` and
:func:`sqrt` here are numpy's, which do not go through MKL. They are slower than MKL for large batches, so the
planners' hot path keeps ``@``; the data layer (contexts, goal poses, IK) uses these.
"""

from __future__ import annotations

import numpy as np
import torch


def _np(fn, x: torch.Tensor) -> torch.Tensor:
    if x.device.type != "cpu" or x.requires_grad:
        return getattr(torch, fn.__name__)(x)  # off the CPU (or under autograd) torch's own is the only one
    return torch.from_numpy(fn(x.detach().numpy())).to(x.dtype)


def sin(x: torch.Tensor) -> torch.Tensor:
    return _np(np.sin, x)


def cos(x: torch.Tensor) -> torch.Tensor:
    return _np(np.cos, x)


def sqrt(x: torch.Tensor) -> torch.Tensor:
    return _np(np.sqrt, x)


def mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for (..., m, k) x (..., k, n) (broadcast batch dimensions), summed over k in order 0, 1, ...:
    ``((a0 b0 + a1 b1) + a2 b2) + ...``, each product and sum rounded once."""
    if a.shape[-1] != b.shape[-2]:
        raise ValueError(f"mm: shapes {tuple(a.shape)} and {tuple(b.shape)} do not chain")
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k : k + 1] * b[..., k : k + 1, :]
    return out


def spd_solve(A: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """x with ``A x = y`` for symmetric positive definite A (..., n, n) and y (..., n): Cholesky ``A = L L^T``
    (outer-product form), then forward and back substitution, every step in a fixed order."""
    n = A.shape[-1]
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        s = A[..., j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        L[j][j] = sqrt(s)
        for i in range(j + 1, n):
            s = A[..., i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            L[i][j] = s / L[j][j]
    z = [None] * n
    for i in range(n):
        s = y[..., i]
        for k in range(i):
            s = s - L[i][k] * z[k]
        z[i] = s / L[i][i]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        s = z[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = s / L[i][i]
    return torch.stack(x, -1)
