"""Self-collision cost: per point the max over the robot's sphere pairs of ReLU(r_i + r_j + eps - d_ij).

``official`` (the authors' CostTaskSpaceCollisionSelf): eps = 0; ``paper``: eps = the task's collision margin.
Integrated over the phase like the other costs. The gradient flows through the deepest pair only (the max):
-+(c_i - c_j)/d_ij on its two centres.

Speed. 100 trajectories x 128 points x 280 Panda pairs are 3.6 M distances per evaluation, while a pair can
only be active where its two links come close, which few configurations do. Spheres fixed to one frame keep
their distances, so a cluster of them has a constant bounding sphere around one of its own centres (radius
R = max_s |c_s - c_ref| + r_s). The bounding spheres of whole frames are tested first (6 pairs for the Panda),
then, where those overlap, those of clusters of <= 3 spheres (4 x 13 pairs). Where every tested pair is
farther apart than R_a + R_b + eps (+ a rounding slack), every sphere pair is inactive by the triangle
inequality, so cost and gradient are exactly 0; only the other configurations (6 % of random Panda
trajectories) get the exact pass over all pairs, as blocks I x J of spheres with equal partner sets (for the
Panda one 8 x 35 block), each a broadcast without index gathers.
"""

from __future__ import annotations

import numpy as np
import torch

from mpd import kernels
from mpd.costs import self_collision_kernel
from mpd.costs.base import Cost, CostInput, CostTerm, register, spheres_vjp_sparse
from mpd.tasks import Task

SLACK = 1e-4  # m: float32 rounding of positions ~1 m is ~1e-7 m, so the test never drops an active pair
CLUSTER = 3  # spheres per cluster: smaller clusters cull better but cost more cluster pairs (measured, Panda)


def biclique_blocks(pairs) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cover a set of pairs (i, j) exactly by blocks I x J: the i with the same set of partners form one I."""
    partners: dict[int, set[int]] = {}
    for i, j in pairs:
        partners.setdefault(int(i), set()).add(int(j))
    by_set: dict[tuple[int, ...], list[int]] = {}
    for i, js in partners.items():
        by_set.setdefault(tuple(sorted(js)), []).append(i)
    return [(np.array(sorted(I)), np.array(J)) for J, I in by_set.items()]


def _clusters(members: np.ndarray, x0: np.ndarray, size: int) -> list[np.ndarray]:
    """Split spheres into clusters of at most ``size`` by halving along the widest axis."""
    out, todo = [], [members]
    while todo:
        m = todo.pop()
        if len(m) <= size:
            out.append(m)
            continue
        c = x0[m]
        order = np.argsort(c[:, np.argmax(c.max(0) - c.min(0))], kind="stable")
        todo += [m[order[: len(m) // 2]], m[order[len(m) // 2 :]]]
    return out


@register
class SelfCollisionCost(Cost):
    name = "self_collision"

    def __init__(self, task: Task, preset: str = "official"):
        super().__init__(task, preset)
        self.margin = 0.0 if preset == "official" else float(task.spec.collision.cost_margin)
        r = self.robot
        pairs = r.self_pairs.numpy()
        radii = r.sphere_radii.numpy()
        used = np.unique(pairs)
        # the exact pass works on the spheres that appear in pairs only, re-indexed 0..len(used)-1
        local = {int(s): k for k, s in enumerate(used)}
        self._used = used
        self.blocks = biclique_blocks([(local[int(i)], local[int(j)]) for i, j in pairs])
        self._radii = radii[used]
        # bounding spheres of whole frames, then of clusters of <= CLUSTER spheres (distances at q = 0)
        x0 = r.sphere_centres(torch.zeros(1, r.dof, dtype=torch.float64))[0].numpy()
        x0 = np.pad(x0, ((0, 0), (0, 3 - x0.shape[1])))
        self._levels = [self._bounding_blocks(pairs, used, x0, radii, size) for size in (len(radii), CLUSTER)]

    def _bounding_blocks(self, pairs, used, x0, radii, size: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Blocks (reference spheres A, reference spheres B, squared reach (|A|, |B|)) of cluster pairs."""
        frame = self.robot.chain.point_joint
        cluster_of = np.full(len(radii), -1)
        ref, reach = [], []
        for f in np.unique(frame[used]):
            for m in _clusters(used[frame[used] == f], x0, size):
                dist = np.linalg.norm(x0[m][:, None] - x0[m][None], axis=-1) + radii[m][None, :]
                best = int(np.argmin(dist.max(1)))
                cluster_of[m] = len(ref)
                ref.append(int(m[best]))
                reach.append(float(dist[best].max()))
        ref, reach = np.array(ref), np.array(reach)
        out = []
        for I, J in biclique_blocks({(cluster_of[i], cluster_of[j]) for i, j in pairs}):
            R = reach[I][:, None] + reach[J][None, :] + self.margin + SLACK
            out.append((ref[I], ref[J], R**2))
        return out

    @classmethod
    def applicable(cls, task: Task) -> bool:
        return bool(task.spec.collision.self_collision) and len(task.robot.self_pairs) > 0

    def _c(self, x: torch.Tensor) -> dict:
        key = ("self", x.dtype, str(x.device))
        if key not in self._consts:
            t = lambda a, **kw: torch.as_tensor(a, device=x.device, **kw)  # noqa: E731
            rr = lambda I, J: self._radii[I][:, None] + self._radii[J][None, :] + self.margin  # noqa: E731
            self._consts[key] = {
                "used": t(self._used),
                "blocks": [(t(I), t(J), t(rr(I, J).reshape(-1, 1), dtype=x.dtype)) for I, J in self.blocks],
                # per level and block: the reference spheres [A | B] (one gather for both) and the squared reach
                "levels": [
                    [(t(np.concatenate([a, b])), len(a), t(R[..., None], dtype=x.dtype)) for a, b, R in level]
                    for level in self._levels
                ],
            }
        return self._consts[key]

    def candidates(self, X: torch.Tensor) -> torch.Tensor:
        """Indices of the configurations (columns of X (S, 3, N)) where some pair may be active: the frames'
        bounding spheres are tested on all of them, the clusters' on those that pass."""
        idx = None
        for level in self._c(X)["levels"]:
            near = None
            for refs, na, reach2 in level:
                XR = X.index_select(0, refs)  # rows first (a copy of contiguous rows), then the few columns
                if idx is not None:
                    XR = XR.index_select(2, idx)
                XA, XB = XR[:na], XR[na:]
                d2 = (XA[:, None, 0] - XB[None, :, 0]).square_()
                for k in (1, 2):
                    diff = XA[:, None, k] - XB[None, :, k]
                    d2.addcmul_(diff, diff)
                hit = d2.sub_(reach2).view(-1, d2.shape[-1]).amin(0) < 0
                near = hit if near is None else near | hit
            sel = near.nonzero().squeeze(1)
            idx = sel if idx is None else idx.index_select(0, sel)
            if idx.numel() == 0:
                break
        return idx

    def deepest_pair(self, Xu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Max over pairs of r_i + r_j + eps - d_ij (M,) and its pair (i, j) (indices into the used spheres),
        for the used spheres' centres Xu (U, 3, M)."""
        best = best_i = best_j = None
        for I, J, rr in self._c(Xu)["blocks"]:
            XA, XB = Xu.index_select(0, I), Xu.index_select(0, J)
            d2 = (XA[:, None, 0] - XB[None, :, 0]).square_()
            for k in (1, 2):
                diff = XA[:, None, k] - XB[None, :, k]
                d2.addcmul_(diff, diff)
            pen = torch.sub(rr, d2.view(len(I) * len(J), -1).sqrt_())
            val, arg = pen.max(0)
            i, j = I[arg // len(J)], J[arg % len(J)]
            if best is None:
                best, best_i, best_j = val, i, j
            else:
                better = val > best
                best = torch.where(better, val, best)
                best_i, best_j = torch.where(better, i, best_i), torch.where(better, j, best_j)
        return best, best_i, best_j

    def _gradient(self, kin, u, config, i, j, ww, n: int) -> torch.Tensor:
        """dC/dq (N, dof) from the deepest pairs (i, j) (sphere indices) of the active configurations, u = c_i - c_j
        (m, 3): d pen / d c_j = weight w u / |u|, minus that on c_i."""
        N = kin.points_t.shape[2]
        coef = ww.index_select(0, config % n)[:, None] / u.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        g = coef * u
        flat = torch.cat([i * N + config, j * N + config])
        return spheres_vjp_sparse(self.robot, kin, flat, torch.cat([-g, g]), N)

    def __call__(self, inp: CostInput, weight: float = 1.0) -> CostTerm:
        B, n, dof = inp.shape
        kin = inp.kinematics()
        X = kin.points_t  # (S, 3, N)
        N = X.shape[2]
        w = self.weights(inp)
        g_q = X.new_zeros(N, dof)
        if kernels.active("self_collision", X):
            key = ("kernel", X.dtype)
            if key not in self._consts:
                r = self.robot
                self._consts[key] = self_collision_kernel.kernel_args(
                    self._levels, self.blocks, self._used, r.sphere_radii.numpy(), self.margin, X.dtype
                )
            # the kernel maps the deepest pairs' gradients to the joints too, given the joints' origins and axes
            grad = (kin, weight * w, self.robot.chain) if kin.origins_t is not None and kin.axes_t is not None else None
            per_point, config, i, j, g_k = self_collision_kernel.self_pass(X, self._consts[key], grad)
            if g_k is not None:
                g_q = g_k
            elif config.numel():
                g_q = self._gradient(kin, X[i, :, config] - X[j, :, config], config, i, j, weight * w, n)
        else:
            per_point = X.new_zeros(N)
            cand = self.candidates(X)
            if cand.numel():
                used = self._c(X)["used"]
                Xu = X.index_select(2, cand).index_select(0, used)  # (U, 3, M): columns first, they are few
                pen, i, j = self.deepest_pair(Xu)
                per_point.index_copy_(0, cand, pen.clamp_min(0))
                sel = (pen > 0).nonzero().squeeze(1)
                if sel.numel():
                    i, j = i.index_select(0, sel), j.index_select(0, sel)
                    u = Xu[i, :, sel] - Xu[j, :, sel]  # (m, 3)
                    g_q = self._gradient(kin, u, cand.index_select(0, sel), used[i], used[j], weight * w, n)
        value = (per_point.view(B, n) * w).sum(-1)
        return CostTerm(value, g_q=g_q.view(B, n, dof))
