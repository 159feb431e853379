"""Batched forward kinematics of serial chains, with analytic Jacobian products.

pytorch-kinematics is the reference (it parses the URDFs and the tests compare against it), but its generic FK is
3-10x slower than needed in the planner's hot path: there, every cost gradient needs the collision-sphere centres of
100 trajectories x 128 points and the transpose-Jacobian product that maps task-space gradients to joint space.
This module folds the fixed joints away once, runs one batched 3x3 product per movable joint, and computes
J^T g for all spheres at once without materialising the (B, S, 3, dof) Jacobian:

    (J^T g)_j = z_j . sum_{s below j} (c_s - o_j) x g_s = z_j . (M_j - o_j x F_j),
    M_j = sum_{s below j} c_s x g_s,  F_j = sum_{s below j} g_s,

for a revolute joint with world axis z_j through o_j (and z_j . F_j for a prismatic one).

Layout: the work is done batch-last, every quantity stored as (rows, B) with the configurations innermost,
so that each per-joint step is one (11, 3) x (3, 3B) product with a long, contiguous inner dimension and every
elementwise op and per-configuration broadcast (sin q_j, cos q_j) is vectorized. The public fields of
:class:`Kinematics` are batch-first views of those buffers; the arithmetic (operands and order of every
sum) is that of the batch-first formulation, and the numbers are bit-identical to it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from mpd import kernels
from mpd.robots import exact as _exact
from mpd.robots import fk_kernel

_NEXT = ((1, 2), (2, 0), (0, 1))  # component k of a x b is a[k1] b[k2] - a[k2] b[k1]


def rpy_to_matrix(rpy: tuple[float, float, float] | np.ndarray) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclass(frozen=True)
class ChainFrame:
    """One link of a serial chain, in order from the root: the joint that carries it and that joint's origin."""

    link: str
    joint: str | None
    joint_type: str  # "revolute" | "prismatic" | "fixed"
    origin: np.ndarray  # (4, 4) pose of the joint frame in the parent link frame
    axis: np.ndarray  # (3,) in the joint frame


@dataclass
class Kinematics:
    """Result of one batched FK pass; holds what the Jacobian products need."""

    q: torch.Tensor  # (B, dof)
    axes: torch.Tensor  # (B, dof, 3) world joint axes
    origins: torch.Tensor  # (B, dof, 3) world joint origins
    points: torch.Tensor  # (B, P, 3) attached points (collision-sphere centres), world frame
    ee_pos: torch.Tensor | None  # (B, 3)
    ee_rot: torch.Tensor | None  # (B, 3, 3)
    # The batch-last buffers the fields above are views of (None for a Kinematics built by hand): what the
    # Jacobian products and the costs read, contiguous with the configurations innermost (the constant axes of a
    # translational chain: a broadcast view). A translational chain keeps no frames (``frames_t`` None).
    axes_t: torch.Tensor | None = None  # (dof, 3, B)
    origins_t: torch.Tensor | None = None  # (dof, 3, B)
    points_t: torch.Tensor | None = None  # (P, 3, B)
    frames_t: torch.Tensor | None = None  # (dof + 1, 4, 3, B): [R_f | p_f] transposed, see KinematicChain.forward

    @classmethod
    def from_batch_last(
        cls,
        q: torch.Tensor,
        axes_t: torch.Tensor,
        origins_t: torch.Tensor,
        points_t: torch.Tensor | None,
        ee_pos: torch.Tensor | None,
        ee_rot: torch.Tensor | None,
        frames_t: torch.Tensor | None,
    ) -> Kinematics:
        """The batch-first fields as views of the batch-last buffers."""
        return cls(
            q,
            axes_t.permute(2, 0, 1),
            origins_t.permute(2, 0, 1),
            None if points_t is None else points_t.permute(2, 0, 1),
            ee_pos,
            ee_rot,
            axes_t=axes_t,
            origins_t=origins_t,
            points_t=points_t,
            frames_t=frames_t,
        )


@dataclass(frozen=True)
class ChainArrays:
    """The constants of a chain that the compiled passes outside torch read (float64 / int64 / bool numpy arrays,
    read-only; see :meth:`KinematicChain.kernel_inputs`): per movable joint j, the Rodrigues terms
    [Off_R, Off_R K, Off_R K^2] (dof, 3, 9), the world-axis and origin offsets (dof, 3, 2) against the parent
    rotation, the fixed rotation Off_R (dof, 3, 3) and the unit axis (dof, 3) in the joint frame; per attached point,
    its frame (P,) (0 = the root, f = after joint f - 1) and position in that frame (P, 3); and the map from the
    stacked frames [R_0 p_0 | ... | R_dof p_dof] to the points (4 (dof + 1), P)."""

    revolute: np.ndarray
    rot_terms: np.ndarray
    axis_off: np.ndarray
    off_r: np.ndarray
    axes: np.ndarray
    point_frame: np.ndarray
    point_local: np.ndarray
    wpoints: np.ndarray


class KinematicChain:
    """A serial chain with points attached to its links.

    The CPU FK of float32 / float64 configurations without autograd runs as one compiled pass
    (:mod:`mpd.robots.fk_kernel`, the kernel ``fk`` of :mod:`mpd.kernels`); in the ``torch`` mode of
    :func:`mpd.kernels.use`, the torch pass, its reference, everywhere.

    Args:
        frames: the chain from the root link to the last link, see :class:`ChainFrame`.
        point_links / point_offsets: the link and link-frame position of every attached point.
        ee_link: the link whose pose is the end-effector pose.
    """

    def __init__(
        self,
        frames: list[ChainFrame],
        point_links: list[str],
        point_offsets: np.ndarray,
        ee_link: str,
    ):
        self.joint_names: list[str] = []
        off_r, off_p, axes, revolute = [], [], [], []
        # link name -> (index of the last movable joint at or above it (-1 = root), fixed 4x4 below that joint)
        attach: dict[str, tuple[int, np.ndarray]] = {frames[0].link: (-1, np.eye(4))}
        acc = np.eye(4)
        last = -1
        for fr in frames[1:]:
            if fr.joint_type == "fixed":
                acc = acc @ fr.origin
            else:
                o = acc @ fr.origin
                off_r.append(o[:3, :3])
                off_p.append(o[:3, 3])
                a = np.asarray(fr.axis, dtype=np.float64)
                axes.append(a / np.linalg.norm(a))
                revolute.append(fr.joint_type == "revolute")
                self.joint_names.append(fr.joint or fr.link)
                acc = np.eye(4)
                last += 1
            attach[fr.link] = (last, acc.copy())
        self.links = list(attach)
        self.dof = len(self.joint_names)
        if ee_link not in attach:
            raise ValueError(f"end-effector link {ee_link!r} is not in the chain ({', '.join(attach)})")
        self.revolute = np.array(revolute, dtype=bool)
        self._off_r = np.stack(off_r)  # (dof, 3, 3)
        self._off_p = np.stack(off_p)  # (dof, 3)
        self._axes = np.stack(axes)  # (dof, 3)
        k = np.asarray(axes)
        kx = np.zeros((self.dof, 3, 3))
        kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
        kx = kx - kx.transpose(0, 2, 1)
        # Rodrigues folded into the joint offset: Off_R Rot(q) = Off_R + sin q Off_R K + (1 - cos q) Off_R K^2,
        # so that R_parent Off_R Rot(q) is one (B*3, 3) x (3, 9) product plus two axpys: batched 3x3 bmm is
        # 10x slower on CPU than a product with a constant.
        self._rot_terms = np.concatenate([self._off_r, self._off_r @ kx, self._off_r @ kx @ kx], axis=2)  # (dof,3,9)
        # the world axis of a joint, R_parent Off_R a, and its origin offset, as a (3, 2) constant
        self._axis_off = np.stack([np.einsum("jab,jb->ja", self._off_r, self._axes), self._off_p], axis=2)

        idx, loc = [], []
        for name, off in zip(point_links, np.asarray(point_offsets, dtype=np.float64).reshape(-1, 3)):
            if name not in attach:
                raise ValueError(f"point on unknown link {name!r} (links: {', '.join(attach)})")
            j, fix = attach[name]
            idx.append(j)
            loc.append(fix[:3, :3] @ off + fix[:3, 3])
        self.point_joint = np.array(idx, dtype=np.int64)  # (P,) -1 = fixed to the root
        self._point_local = np.array(loc).reshape(-1, 3)
        # descendant mask: D[s, j] = 1 when point s moves with joint j
        self._desc = (self.point_joint[:, None] >= np.arange(self.dof)[None, :]).astype(np.float64)
        # Block-sparse map from the stacked [R | p] of all frames to the attached points, so that every point
        # centre comes out of one dense matmul: points^T = [R_0 p_0 | ... | R_dof p_dof] (3, 4(dof+1)) @ W.
        W = np.zeros((self.dof + 1, 4, len(idx)))
        for s_, (j_, c_) in enumerate(zip(self.point_joint, self._point_local)):
            W[j_ + 1, :3, s_] = c_
            W[j_ + 1, 3, s_] = 1.0
        self._wpoints = W.reshape(4 * (self.dof + 1), len(idx))
        # Points sorted by frame (the usual case) get one small product per frame, written straight into its
        # rows of the output, instead of the dense product with W (8x fewer flops, the same non-zero terms).
        self._point_blocks: list[tuple[int, int, int]] | None = None
        pj = self.point_joint
        if len(pj) and np.all(np.diff(pj) >= 0):
            self._point_blocks = [
                (int(f), int(np.searchsorted(pj, f - 1, "left")), int(np.searchsorted(pj, f - 1, "right")))
                for f in np.unique(pj + 1)
            ]
        j, fix = attach[ee_link]
        self.ee_joint = j
        self._ee_fix = fix
        self._cache: dict[tuple, dict[str, torch.Tensor]] = {}
        # A chain of prismatic joints only (the point mass, gantries) never rotates: every frame's rotation, every
        # joint axis and the end-effector's rotation are constants, and the joint origins, end-effector position
        # and points are affine in q: [origins; ee position; points] = b + A q, with b and A read off the general
        # pass at q = 0 and q = e_j (exact up to float64 rounding). Its FK is dof fused multiply-adds (no frames
        # are kept), and every Jacobian product is one with the constant axes.
        self._affine: tuple[np.ndarray, ...] | None = None
        if self.dof and not self.revolute.any():
            q = torch.cat([torch.zeros(1, self.dof), torch.eye(self.dof)]).to(torch.float64)
            k = self._forward_general(q, points=True, ee=True, exact=True)
            rows = torch.cat(
                [k.origins_t.reshape(-1, self.dof + 1), k.ee_pos.t(), k.points_t.reshape(-1, self.dof + 1)]
            )
            rows = rows.numpy()
            b, A = rows[:, 0].copy(), rows[:, 1:] - rows[:, :1]
            self._affine = (b, A, k.axes_t[:, :, 0].numpy().copy(), k.ee_rot[0].numpy().copy())
            self._cache.clear()  # the constants made by that pass lack the affine ones

    @functools.cached_property
    def reach(self) -> float | None:
        """An upper bound of |c| over all configurations and attached points c (root frame), or None when a
        prismatic joint makes it unbounded: each joint offset and point offset adds at most its length (computed
        once: the collision cost asks for it on every call)."""
        if not self.revolute.all():
            return None
        offsets = np.concatenate([[0.0], np.cumsum(np.linalg.norm(self._off_p, axis=1))])
        bounds = offsets[self.point_joint + 1] + np.linalg.norm(self._point_local, axis=1)
        return float(bounds.max()) if len(bounds) else 0.0

    @functools.cached_property
    def _arrays(self) -> ChainArrays:
        def ro(a: np.ndarray) -> np.ndarray:
            a = np.array(a)  # a copy, read-only
            a.flags.writeable = False
            return a

        return ChainArrays(
            revolute=ro(self.revolute),
            rot_terms=ro(self._rot_terms),
            axis_off=ro(self._axis_off),
            off_r=ro(self._off_r),
            axes=ro(self._axes),
            point_frame=ro(self.point_joint + 1),
            point_local=ro(self._point_local),
            wpoints=ro(self._wpoints),
        )

    def kernel_inputs(self) -> ChainArrays:
        """The chain's constants for a compiled pass outside torch (:class:`ChainArrays`, made once)."""
        return self._arrays

    # ------------------------------------------------------------------ constants per dtype/device
    def _c(self, dtype: torch.dtype, device: torch.device) -> dict[str, torch.Tensor]:
        key = (dtype, str(device))
        if key not in self._cache:
            t = lambda a: torch.as_tensor(a, dtype=dtype, device=device)  # noqa: E731
            self._cache[key] = {
                "off_r": t(self._off_r),
                "off_p": t(self._off_p),
                "axes": t(self._axes),
                "rot_terms": t(self._rot_terms),
                "axis_off": t(self._axis_off),
                "wpoints": t(self._wpoints),
                "desc": t(self._desc),
                "ee_r": t(self._ee_fix[:3, :3]),
                "ee_p": t(self._ee_fix[:3, 3]),
                # batch-last forms: row c of (R K)^T is K[:, c]^T R^T, so the constants are transposed
                "joint_t": t(np.concatenate([self._rot_terms, self._axis_off], 2).transpose(0, 2, 1).copy()),
                "axes_row": t(self._axes[:, None, :].copy()),  # (dof, 1, 3)
                "wpoints_t": t(self._wpoints.T.copy()),  # (P, 4 (dof+1))
                "desc_t": t(self._desc.T.copy()),  # (dof, P)
                "ee_r_t": t(self._ee_fix[:3, :3].T.copy()),
                "ee_p_row": t(self._ee_fix[None, :3, 3].copy()),
                "revolute": torch.as_tensor(self.revolute, device=device)[:, None, None],
            }
            if self._affine is not None:
                b, A, z, ee_rot = self._affine
                self._cache[key].update(
                    aff_b=t(b[:, None].copy()),
                    aff_A=t(A.T[:, :, None].copy()),
                    aff_z=t(z[:, :, None]),
                    aff_ee_rot=t(ee_rot),
                )
        return self._cache[key]

    # ------------------------------------------------------------------ forward kinematics
    def forward(self, q: torch.Tensor, *, points: bool = True, ee: bool = True, exact: bool = False) -> Kinematics:
        """FK for q of shape (B, dof). ``exact``: every product written out in a fixed order
        (:mod:`mpd.robots.exact`), the same bits on every CPU, instead of MKL's processor-specific kernels (the
        data-generation path; slower)."""
        if q.shape[-1] != self.dof:
            raise ValueError(f"expected configurations with {self.dof} joints, got shape {tuple(q.shape)}")
        if self._affine is not None and not exact:
            return self._forward_affine(q, points, ee)
        return self._forward_general(q, points, ee, exact)

    def _forward_affine(self, q: torch.Tensor, points: bool, ee: bool) -> Kinematics:
        """FK of a chain without revolute joints: [origins; ee position; points] = b + sum_j A_j q_j (no frames)."""
        c = self._c(q.dtype, q.device)
        B, dof, P = q.shape[0], self.dof, len(self.point_joint)
        n = 3 * dof + 3 + (3 * P if points else 0)  # the rows computed (those of the ee position are few)
        A, b = c["aff_A"][:, :n], c["aff_b"][:n]
        # elementwise, not a (rows, dof) x (dof, B) product: the BLAS product of so short an inner dimension was up
        # to 5x slower in some processes on the 2-core CPU (the same in all others)
        out = torch.addcmul(b, A[0], q[:, 0])
        for j in range(1, dof):
            out.addcmul_(A[j], q[:, j])
        origins = out[: 3 * dof].view(dof, 3, B)
        pts_t = out[3 * dof + 3 :].view(P, 3, B) if points else None
        ee_pos = out[3 * dof : 3 * dof + 3].t() if ee else None
        ee_rot = c["aff_ee_rot"].expand(B, 3, 3) if ee else None
        return Kinematics.from_batch_last(q, c["aff_z"].expand(dof, 3, B), origins, pts_t, ee_pos, ee_rot, None)

    def _kernel_points(self, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray]:
        """(frame (P,), [l; 1] weights (P, 4)) of the points for the compiled FK pass (empty without points)."""
        key = ("kernel_points", dtype)
        if key not in self._cache:
            mw = self.point_moments_weights(dtype)
            self._cache[key] = mw if mw is not None else (np.zeros(0, np.int64), np.zeros((0, 4)))
        return self._cache[key]

    @property
    def translational(self) -> bool:
        """True for a chain without revolute joints: constant axes, affine FK, no frames kept (``frames_t`` None);
        its Jacobian products need only the forces (row 3 of :meth:`vjp_from_moments`' moments)."""
        return self._affine is not None

    @property
    def ee_fixed(self) -> np.ndarray:
        """The end effector's pose (4, 4) in the frame of the last joint that moves it (float64, read-only)."""
        out = self._ee_fix.view()
        out.flags.writeable = False
        return out

    def points_jacobian(self) -> np.ndarray | None:
        """The attached points' Jacobians (P, 3, dof), constant for a chain without revolute joints (the A of its
        affine FK); None for any other chain."""
        if self._affine is None:
            return None
        A = self._affine[1]  # rows [origins (3 dof); ee position (3); points (3 P)] x dof
        return np.ascontiguousarray(A[3 * self.dof + 3 :].reshape(-1, 3, self.dof))

    def _affine_vjp(self, F: torch.Tensor) -> torch.Tensor:
        """(B, dof) J^T g of a chain without revolute joints from F (dof, 3, B), F_j = the sum of the gradients on
        the points that joint j moves: (J^T g)_j = z_j . F_j."""
        return (F * self._c(F.dtype, F.device)["aff_z"]).sum(1).t().contiguous()

    def _forward_general(self, q: torch.Tensor, points: bool, ee: bool, exact: bool) -> Kinematics:
        c = self._c(q.dtype, q.device)
        mm = _exact.mm if exact else torch.matmul
        B, dof = q.shape[0], self.dof
        if not exact and (self._point_blocks is not None or not points) and kernels.active("fk", q):
            # the compiled pass (the torch lines below are its reference)
            frame, W = self._kernel_points(q.dtype)
            qt = q.t().contiguous()
            F, axes, origins, pts_t = fk_kernel.fk_pass(c["joint_t"], self.revolute, c["axes"], qt, W, frame, points)
            ee_pos, ee_rot = self._ee_pose(F, c) if ee else (None, None)
            return Kinematics.from_batch_last(q, axes, origins, pts_t, ee_pos, ee_rot, F)
        # Frames, batch-last: F[f, b, a, :] = R_f[a, b] (b < 3) and F[f, 3, a, :] = p_f[a], so that F[f]
        # viewed as (4, 3B) is the (transposed) [R | p] block of every configuration, and right-multiplying a
        # frame by a constant is one product with a long inner dimension.
        F = q.new_empty(dof + 1, 4, 3, B)
        F[0].zero_()
        for a in range(3):
            F[0, a, a] = 1.0
        # Autograd cannot record ops that write into an out= buffer, nor use views of a buffer written later:
        # when q needs a gradient, every frame is a fresh tensor that is copied into F (the same arithmetic).
        track = q.requires_grad and torch.is_grad_enabled()
        qt = q.t().contiguous()
        s, co = (_exact.sin(qt), 1 - _exact.cos(qt)) if exact else (torch.sin(qt), 1 - torch.cos(qt))
        axes = q.new_empty(dof, 3, B)
        origins = q.new_empty(dof, 3, B)
        R = F[0, :3].clone() if track else F[0, :3]
        for j in range(dof):
            # rows: R Off_R, R Off_R K, R Off_R K^2 (Rodrigues terms), the world axis, R_parent off_p
            P = mm(c["joint_t"][j], R.reshape(3, 3 * B)).view(11, 3, B)
            o = F[j, 3] + P[10]
            if self.revolute[j]:
                Rn = torch.addcmul(P[0:3], s[j], P[3:6], out=None if track else F[j + 1, :3])
                Rn.addcmul_(co[j], P[6:9])
                ax, pn = P[9], o
            else:
                Rn = P[0:3]
                ax = mm(c["axes_row"][j], Rn.reshape(3, 3 * B)).view(3, B)
                pn = torch.addcmul(o, ax, qt[j])
            if track or not self.revolute[j]:
                F[j + 1, :3] = Rn
            F[j + 1, 3] = pn
            axes[j] = ax
            origins[j] = o
            R = Rn
        pts_t = None
        if points:
            Fm = F.view(4 * (dof + 1), 3 * B)
            if exact:
                pts_t = mm(c["wpoints_t"], Fm).view(-1, 3, B)
            elif self._point_blocks is None:
                pts_t = (c["wpoints_t"] @ Fm).view(-1, 3, B)
            else:
                # one small product per frame, written into its rows of the output (concatenated for autograd)
                blocks = [
                    (c["wpoints_t"][lo:hi, 4 * f : 4 * f + 4], Fm[4 * f : 4 * f + 4], lo, hi)
                    for f, lo, hi in self._point_blocks
                ]
                if track:
                    pts_t = torch.cat([w @ x for w, x, _, _ in blocks]).view(-1, 3, B)
                else:
                    pts_t = q.new_empty(len(self.point_joint), 3, B)
                    for w, x, lo, hi in blocks:
                        torch.mm(w, x, out=pts_t[lo:hi].view(hi - lo, 3 * B))
        ee_pos, ee_rot = self._ee_pose(F, c, mm) if ee else (None, None)
        return Kinematics.from_batch_last(q, axes, origins, pts_t, ee_pos, ee_rot, F)

    def _ee_pose(self, F: torch.Tensor, c: dict, mm=torch.matmul) -> tuple[torch.Tensor, torch.Tensor]:
        """End-effector position (B, 3) and rotation (B, 3, 3) from the batch-last frames F."""
        B = F.shape[-1]
        Re = F[self.ee_joint + 1, :3].reshape(3, 3 * B)
        ee_rot = mm(c["ee_r_t"], Re).view(3, 3, B).permute(2, 1, 0)
        ee_pos = (F[self.ee_joint + 1, 3] + mm(c["ee_p_row"], Re).view(3, B)).t()
        return ee_pos, ee_rot

    def select(self, kin: Kinematics, idx: torch.Tensor, points: bool = True) -> Kinematics:
        """The kinematics of the configurations ``idx`` of a batch, end-effector pose included: a gather of the
        batch-last buffers instead of a second FK pass (the costs need the final configurations' EE pose, whose
        frames the collision costs' FK of all configurations already holds). ``points``: False leaves the attached
        points out (the largest of the buffers; the end-effector cost does not read them)."""
        if kin.frames_t is None:
            return self.forward(kin.q.index_select(0, idx), points=points)
        F = kin.frames_t.index_select(3, idx)
        axes, origins = kin.axes_t.index_select(2, idx), kin.origins_t.index_select(2, idx)
        pts = None if kin.points_t is None or not points else kin.points_t.index_select(2, idx)
        ee_pos, ee_rot = self._ee_pose(F, self._c(F.dtype, F.device))
        return Kinematics.from_batch_last(kin.q.index_select(0, idx), axes, origins, pts, ee_pos, ee_rot, F)

    # ------------------------------------------------------------------ Jacobian products
    def points_vjp(self, kin: Kinematics, g: torch.Tensor) -> torch.Tensor:
        """J^T g for g = dC/d(points) of shape (B, P, 3): returns dC/dq (B, dof).

        Fastest when g is a view of a batch-last (P, 3, B) buffer (``buf.permute(2, 0, 1)``), the layout of
        ``kin.points_t``: then nothing is copied.
        """
        c = self._c(g.dtype, g.device)
        B = g.shape[0]
        y = g.permute(1, 2, 0)
        if not y.is_contiguous():
            y = y.contiguous()
        if self._affine is not None:
            return self._affine_vjp((c["desc_t"] @ y.view(-1, 3 * B)).view(-1, 3, B))
        x = kin.points_t if kin.points_t is not None else kin.points.permute(1, 2, 0).contiguous()
        m = torch.empty_like(y)  # (P, 3, B): c x g
        for k, (k1, k2) in enumerate(_NEXT):
            torch.mul(x[:, k1], y[:, k2], out=m[:, k])
            m[:, k].sub_(x[:, k2] * y[:, k1])
        F = (c["desc_t"] @ y.view(-1, 3 * B)).view(-1, 3, B)  # (dof, 3, B)
        M = (c["desc_t"] @ m.view(-1, 3 * B)).view(-1, 3, B)
        o = kin.origins_t if kin.origins_t is not None else kin.origins.permute(1, 2, 0)
        z = kin.axes_t if kin.axes_t is not None else kin.axes.permute(1, 2, 0)
        # o x F, written as torch.linalg.cross computes it (a fused multiply-add per component, which addcmul
        # also uses), 3x faster than linalg.cross along a non-innermost dimension
        rev = torch.stack([torch.addcmul(-(o[:, k2] * F[:, k1]), o[:, k1], F[:, k2]) for k1, k2 in _NEXT], 1)
        # (the selection is skipped when every joint is revolute: the same numbers, without a slow torch.where)
        out = (M - rev if self.revolute.all() else torch.where(c["revolute"], M - rev, F)) * z
        return (out[:, 0] + out[:, 1] + out[:, 2]).t().contiguous()

    def points_vjp_frames(self, kin: Kinematics, g: torch.Tensor) -> torch.Tensor:
        """J^T g like :meth:`points_vjp`, for a batch-last g (P, 3, B), from the frames instead of the points.

        For the points s on frame f, c_s = R_f l_s + p_f, so sum_s c_s g_s^T = [R_f | p_f] H_f with
        H_f = sum_s [l_s; 1] g_s^T: one product with a constant per frame (the transpose of the FK's point
        product), and F_f = sum_s g_s is the last row of H_f. M_f = sum_s c_s x g_s is the axial part of
        sum_s c_s g_s^T. This reads g once instead of forming c x g for every point: 2x faster on the
        100 x 128 Panda points, equal to :meth:`points_vjp` up to rounding (the sums run in another order).
        Needs sorted points (see ``_point_blocks``) and ``kin.frames_t``; falls back to :meth:`points_vjp`.
        """
        if self._point_blocks is None or kin.frames_t is None:
            return self.points_vjp(kin, g.permute(2, 0, 1))
        c = self._c(g.dtype, g.device)
        dof, B = self.dof, g.shape[2]
        # frames 1..dof (points on the root frame move with no joint); rows of frames without points stay 0
        covered = sum(1 for f, _, _ in self._point_blocks if f > 0) == dof
        H = g.new_empty(dof, 4, 3, B) if covered else g.new_zeros(dof, 4, 3, B)
        gm = g.reshape(-1, 3 * B)
        for f, lo, hi in self._point_blocks:
            if f > 0:
                w = c["wpoints_t"][lo:hi, 4 * f : 4 * f + 4]
                torch.mm(w.t(), gm[lo:hi], out=H[f - 1].view(4, 3 * B))
        return self.vjp_from_moments(kin, H)

    def point_moments_weights(self, dtype: torch.dtype) -> tuple[np.ndarray, np.ndarray] | None:
        """(frame of each point (P,), its [l; 1] weights (P, 4)): the point products of the compiled FK, and the
        weights of the moments H of :meth:`vjp_from_moments`; None when the chain has no sorted points."""
        if self._point_blocks is None:
            return None
        W = self._c(dtype, torch.device("cpu"))["wpoints_t"].numpy()
        frame = self.point_joint + 1
        rows = np.stack([W[s, 4 * f : 4 * f + 4] for s, f in enumerate(frame)])
        return frame.astype(np.int64), np.ascontiguousarray(rows)

    def vjp_from_moments(self, kin: Kinematics, H: torch.Tensor) -> torch.Tensor:
        """J^T g (B, dof) from the per-frame moments H (dof, 4, 3, B), H[f - 1, m, k] = sum over the points s on frame
        f of [l_s; 1][m] g_s[k] (see :meth:`points_vjp_frames`); H is overwritten."""
        dof, B = self.dof, H.shape[3]
        if self._affine is not None:  # constant axes: only the forces count
            return self.vjp_from_forces(kin, H[:, 3], None)
        T = kin.frames_t[1:]  # T[f, m, i] = [R_f | p_f][i, m]
        # M_f = sum_m T[:, m] x H[:, m], accumulated in place (fused multiply-adds on (dof, B) rows, no temporaries)
        M = H.new_empty(dof, 3, B)
        for k, (k1, k2) in enumerate(_NEXT):
            Mk = torch.mul(T[:, 0, k1], H[:, 0, k2], out=M[:, k])
            Mk.addcmul_(T[:, 0, k2], H[:, 0, k1], value=-1)
            for m in (1, 2, 3):
                Mk.addcmul_(T[:, m, k1], H[:, m, k2]).addcmul_(T[:, m, k2], H[:, m, k1], value=-1)
        return self.vjp_from_forces(kin, H[:, 3], M)

    def vjp_from_forces(self, kin: Kinematics, F: torch.Tensor, M: torch.Tensor | None) -> torch.Tensor:
        """J^T g (B, dof) from the sums over the points s on each frame f (dof, 3, B; overwritten): F_f = sum g_s and
        M_f = sum c_s x g_s (world-frame centres c_s; M may be None on a translational chain, which reads only F).
        With the sums over the frames j+1..dof that joint j moves, (J^T g)_j = z_j . (M_j - o_j x F_j) for a revolute
        joint and z_j . F_j for a prismatic one (the compiled collision pass accumulates F and M directly)."""
        c = self._c(F.dtype, F.device)
        for j in range(self.dof - 2, -1, -1):  # joint j moves the frames j+1..dof
            F[j] += F[j + 1]
            if self._affine is None:
                M[j] += M[j + 1]
        if self._affine is not None:
            return self._affine_vjp(F)
        o, z = kin.origins_t, kin.axes_t
        if self.revolute.all():
            for k, (k1, k2) in enumerate(_NEXT):  # M - o x F, in place
                M[:, k].addcmul_(o[:, k1], F[:, k2], value=-1).addcmul_(o[:, k2], F[:, k1])
        else:
            rev = torch.stack([o[:, k1] * F[:, k2] - o[:, k2] * F[:, k1] for k1, k2 in _NEXT], 1)
            M = torch.where(c["revolute"], M - rev, F)
        out = M[:, 0] * z[:, 0]
        out.addcmul_(M[:, 1], z[:, 1]).addcmul_(M[:, 2], z[:, 2])
        return out.t().contiguous()

    def ee_jacobian(self, kin: Kinematics) -> torch.Tensor:
        """Geometric Jacobian of the end effector in the world frame, rows [v; w]: (B, 6, dof)."""
        B = kin.q.shape[0]
        J = torch.zeros(B, 6, self.dof, dtype=kin.q.dtype, device=kin.q.device)
        n = self.ee_joint + 1  # joints that move the end effector
        if n == 0:
            return J
        z, o = kin.axes[:, :n], kin.origins[:, :n]
        rev = torch.as_tensor(self.revolute[:n], device=z.device)[None, :, None]
        lin = torch.where(rev, torch.linalg.cross(z, kin.ee_pos[:, None, :] - o), z)
        ang = torch.where(rev, z, torch.zeros_like(z))
        J[:, :3, :n] = lin.transpose(1, 2)
        J[:, 3:, :n] = ang.transpose(1, 2)
        return J
