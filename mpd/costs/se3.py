"""SO(3)/SE(3) logarithms and the exact gradients of the end-effector pose costs, batched, without autograd.

Conventions: twists are ordered [v; w] (translation first, like Theseus' ``SE3.log``), exp(xi) = [[Exp(w),
V(w) v], [0, 1]] with V = J_l the left Jacobian of SO(3), so log(R, t) = (V(phi)^-1 t, phi) with phi = Log(R).
"""

from __future__ import annotations

import torch


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a x b over the last dimension (3), for tensors of any broadcastable shape."""
    return torch.linalg.cross(*torch.broadcast_tensors(a, b), dim=-1)


def series_below(dtype: torch.dtype) -> float:
    """The angle below which the logarithm's coefficients are their series (also the compiled EE pass's): below it
    the closed forms lose more digits to cancellation than the series' truncation error."""
    return 0.05 if dtype == torch.float64 else 0.5


def so3_log(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation vector phi (..., 3) and angle theta = |phi| (...) of rotation matrices R (..., 3, 3).

    theta = atan2(|w|, (tr R - 1) / 2) with w = vee(R - R^T) / 2 = sin(theta) n is accurate at every angle;
    the axis comes from w except near pi, where w vanishes and the symmetric part (R + R^T)/2 - cos(theta) I =
    (1 - cos(theta)) n n^T gives it (its largest column, signed to agree with w).
    """
    w = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1) / 2
    cos = ((R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]) - 1) / 2
    sin = w.norm(dim=-1)
    theta = torch.atan2(sin, cos)
    t2 = theta * theta
    series = 1 + t2 / 6 + 7 * t2 * t2 / 360 + 31 * t2 * t2 * t2 / 15120  # theta / sin(theta)
    scale = torch.where(theta < series_below(R.dtype), series, theta / sin.clamp_min(1e-30))
    phi = scale[..., None] * w
    near_pi = cos < -0.9
    if bool(near_pi.any()):
        one_m_cos = (1 - cos)[..., None, None]
        Bm = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * torch.eye(3, dtype=R.dtype, device=R.device)
        diag = torch.diagonal(Bm, dim1=-2, dim2=-1)
        k = diag.argmax(-1)
        col = torch.gather(Bm, -1, k[..., None, None].expand(*k.shape, 3, 1))[..., 0]
        n = col / (torch.gather(diag, -1, k[..., None]) * one_m_cos[..., 0]).clamp_min(1e-30).sqrt()
        n = torch.where(((n * w).sum(-1) < 0)[..., None], -n, n)
        phi = torch.where(near_pi[..., None], theta[..., None] * n, phi)
    return phi, theta


def _vinv_coeffs(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """c(theta) and c'(theta)/theta in V^-1 = I - phi^/2 + c phi^ phi^, c = 1/theta^2 - cot(theta/2)/2theta.

    Near 0 both closed forms cancel catastrophically, so their Taylor series take over there.
    """
    t2 = theta * theta
    c_series = 1 / 12 + t2 / 720 + t2 * t2 / 30240 + t2 * t2 * t2 / 1209600
    dc_series = 1 / 360 + t2 / 7560 + t2 * t2 / 201600
    small = theta < series_below(theta.dtype)
    t = torch.where(small, torch.ones_like(theta), theta)  # keep the unused branch finite
    half_sin, half_cos = torch.sin(t / 2), torch.cos(t / 2)
    cot = half_cos / half_sin
    c = 1 / (t * t) - cot / (2 * t)
    dc = -2 / t**4 + cot / (2 * t**3) + 1 / (4 * t * t * half_sin * half_sin)
    return torch.where(small, c_series, c), torch.where(small, dc_series, dc)


def se3_log(R: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Twist xi = [rho; phi] (..., 6) of the poses (R, t); also returns the pieces the gradient reuses."""
    phi, theta = so3_log(R)
    c, dc = _vinv_coeffs(theta)
    pt = cross(phi, t)
    rho = t - pt / 2 + c[..., None] * cross(phi, pt)
    return torch.cat([rho, phi], -1), {"phi": phi, "rho": rho, "c": c, "dc": dc, "t": t, "R": R}


def se3_half_sq_log_grad(parts: dict[str, torch.Tensor]) -> torch.Tensor:
    """Gradient (..., 6), ordered [v; w], of f(eps) = 1/2 |log(E exp(eps))|^2 at eps = 0 (right perturbation).

    With E = (R, t), phi = Log R, rho = V^-1(phi) t and E exp(eps) = (R Exp(eps_w), t + R eps_v) + O(eps^2):
        d phi = J_r^-1(phi) eps_w,   d rho = V^-1 R eps_v + D d phi,   D = d(V^-1(phi) t)/d phi
    so, using J_r^-T(phi) = J_l^-1(phi) = V^-1 and V^-1 phi = phi,
        df/d eps_v = R^T V^-T rho,    df/d eps_w = phi + V^-1 D^T rho,
    where, from V^-1 t = t - phi x t / 2 + c(theta) phi x (phi x t),
    phi x (phi x t) = phi (phi.t) - t theta^2 and dc/dphi = c'(theta) phi^T / theta:
        D = t^/2 + c ((phi.t) I + phi t^T - 2 t phi^T) + (c'/theta) (phi x (phi x t)) phi^T.
    The rotation part alone (t = 0) is phi: the SO(3) fact J_l^-1(phi) phi = phi. The translation part is NOT
    rho in general: for SE(3), J_r^-T(xi) xi = xi only when ad_xi^T xi = [w x v; 0] = 0, i.e. for pure
    rotations, pure translations or v parallel to w. So the authors' -J^T xi is the gradient of 1/2|xi|^2 only
    to first order in |xi| (it is exact at the goal, where both vanish); this function is exact.
    """
    phi, rho, c, dc, t, R = (parts[k] for k in ("phi", "rho", "c", "dc", "t", "R"))
    c3, dc3 = c[..., None], dc[..., None]
    pt = cross(phi, t)
    ppt = cross(phi, pt)
    dot = lambda a, b: (a * b).sum(-1, keepdim=True)  # noqa: E731
    Dt_rho = (
        cross(rho, t) / 2
        + c3 * (dot(phi, t) * rho + t * dot(phi, rho) - 2 * phi * dot(t, rho))
        + dc3 * phi * dot(ppt, rho)
    )
    # V^-1 y = y - phi x y / 2 + c phi x (phi x y); V^-T y flips the sign of the odd term
    py = cross(phi, Dt_rho)
    g_w = phi + Dt_rho - py / 2 + c3 * cross(phi, py)
    pr = cross(phi, rho)
    vt_rho = rho + pr / 2 + c3 * cross(phi, pr)
    g_v = (R.transpose(-1, -2) @ vt_rho[..., None])[..., 0]
    return torch.cat([g_v, g_w], -1)
