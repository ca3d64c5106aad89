"""The solver's frame API, as a mixin of ``QuasiStaticSolver`` (solver.py): start, solve a frame in load sub-steps,
snapshot and restore.

A frame moves the indenters from the last poses to new ones (4x4, indenter frame -> gel frame, mm). Its motion is
solved as load (sub)steps (newton.py ``_solve_step``), the poses interpolated between the two (translation linearly,
rotation by slerp). A step that does not converge (or, where it can still be halved, creeps: convergence_tests.py
``StallWatch``), ends out of equilibrium (|gradient| above ``max_residual_n``) or leaves a penetration above
``penetration_tol_mm`` is retried with half the pose increment from the last converged sub-step, and the rest of the
frame goes on in steps of that size (adaptive load sub-stepping, down to 1/2**``max_substep_halvings`` of the frame);
past that, ``SolverDidNotConverge`` says which frame, which indenters and what was tried, and u and friction's stretch
are put back as they were at the frame's start (the contact stiffness keeps any raise, and the warm start's last
increment is that of the last converged sub-step). Nothing half-solved is ever returned.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation, Slerp

from transtac_sim.physics.settings import (
    FailedStep,
    FrameResult,
    IndenterStartsInsideGel,
    SolverDidNotConverge,
    SolverRecord,
)


def _interpolate_pose(A: np.ndarray, B: np.ndarray, t: float) -> np.ndarray:
    """The pose a fraction ``t`` of the way from A to B (4x4): the translation linearly, the rotation by slerp."""
    P = np.eye(4)
    P[:3, 3] = (1.0 - t) * A[:3, 3] + t * B[:3, 3]
    rots = Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]]))
    P[:3, :3] = Slerp([0.0, 1.0], rots)([t]).as_matrix()[0]
    return P


class LoadStepping:
    """The frame API for ``QuasiStaticSolver`` (which provides the fields, the indenters, the Newton steps and the
    records of a solution)."""

    def start(self, poses: list[np.ndarray]) -> None:
        """Reset to the undeformed gel with the indenters at ``poses``; they must not penetrate it."""
        poses = self._check_poses(poses)
        self.u.dof_values.zero_()
        self.u_prev.dof_values.zero_()
        self.u_lag.dof_values.zero_()
        self._contact_state.stick_next.zero_()
        for i in range(len(poses)):
            depth = self._max_penetration(self._indenter_struct([poses[i]], [poses[i]], which=[i], role="probe"))
            if depth > self.settings.penetration_tol_mm:
                raise IndenterStartsInsideGel(
                    f"indenter {self.indenters[i].name!r} starts {depth:.4g} mm inside the undeformed gel "
                    f"(tolerance {self.settings.penetration_tol_mm} mm); start it above the surface z = "
                    f"{self.vertices_mm[:, 2].max():.4g} mm"
                )
        self._poses = poses
        self._increment = None
        self.frame_index = 0

    def _check_poses(self, poses) -> list[np.ndarray]:
        poses = [np.asarray(P, dtype=np.float64) for P in poses]
        if len(poses) != len(self.indenters) or any(P.shape != (4, 4) for P in poses):
            raise ValueError(f"expected {len(self.indenters)} poses of shape (4,4)")
        return poses

    def solve_frame(self, poses: list[np.ndarray]) -> FrameResult:
        """Move the indenters to ``poses`` (one 4x4 each) and solve the static equilibrium."""
        if self._poses is None:
            raise RuntimeError("call start(initial_poses) before solve_frame")
        poses = self._check_poses(poses)
        t0 = time.perf_counter()
        frame = self.frame_index
        self.stats = Counter()
        u_frame_start, stick_frame_start = self._frame_start
        wp.copy(u_frame_start, self.u.dof_values)
        wp.copy(stick_frame_start, self._contact_state.stick_next)
        tried = []
        total_iterations, steps = 0, 0
        # the frame's motion in units of 1/2**max_substep_halvings: from `done` in steps of `size` (halved at a failure)
        whole = 2**self.settings.max_substep_halvings
        done, size, prev, ok = 0, whole, self._poses, True
        while done < whole:
            size = min(size, whole - done)
            target = [_interpolate_pose(A, B, (done + size) / whole)
                      for A, B in zip(self._poses, poses, strict=False)]
            wp.copy(self.u_prev.dof_values, self.u.dof_values)  # the last converged state: Newton starts there
            wp.copy(self._contact_state.stick, self._contact_state.stick_next)  # and friction's stretch there
            ok, it, why, pen = self._solve_step(target, prev, may_stall=size > 1)
            total_iterations += it
            if ok and pen > self.settings.penetration_tol_mm:
                ok, why = False, f"penetration {pen:.3g} mm above the tolerance"
            # the frame's record keeps the last accepted sub-step's |gradient|
            limit = self.settings.max_residual_n
            if ok and not (residual := self._free_norm(self._gradient(self._last_ind))) <= limit:
                ok, why = False, (f"Newton ended out of equilibrium: |gradient| {residual:.3g} N above max_residual_n = "
                                  f"{limit:g} N, smallest det F {self._min_det(self.u):.3g}")
            if ok:
                self._keep_stick(self._last_ind)
                done, prev, steps = done + size, target, steps + 1
                continue
            tried.append(FailedStep(done / whole, (done + size) / whole, it, why))
            wp.copy(self.u.dof_values, self.u_prev.dof_values)
            if size == 1:
                break
            size //= 2
        if not ok:
            wp.copy(self.u.dof_values, u_frame_start)
            wp.copy(self._contact_state.stick_next, stick_frame_start)
            names = ", ".join(repr(i.name) for i in self.indenters)
            raise SolverDidNotConverge(
                f"frame {frame} (indenters {names}) did not converge with sub-steps down to 1/{whole} of its motion; "
                "tried: " + "; ".join(map(str, tried)) + f". Settings: newton_tol_mm={self.settings.newton_tol_mm}, "
                f"max_newton_iterations={self._newton_iteration_cap()}, "
                f"max_substep_halvings={self.settings.max_substep_halvings}, "
                f"contact stiffness {self.contact_stiffness:.4g} N/mm^3"
            )
        lag_residual, wrench, min_det = self._frame_records(self._last_ind)
        record = SolverRecord(
            converged=True,
            iterations=total_iterations,
            residual=residual,
            friction_lag_residual_n=lag_residual,
            min_det_f=min_det,  # > 0: no step that inverts an element is ever accepted
            seconds=time.perf_counter() - t0,
            substeps=steps,
            max_penetration_mm=pen,
            linear_iterations=self._linear.last_iterations,
            backtracks=self.stats["backtracks"],
            stiffness_raises=self.stats["stiffness_raises"],
            warm_starts=self.stats["warm_starts"],
            lag_updates=self.stats["lag_updates"],
            indefinite_hessians=self.stats["indefinite_hessians"],
            predicted_contacts=self.stats["predicted_contacts"],
            failed_steps=tuple(tried),
        )
        self._poses = poses
        self.frame_index += 1
        return FrameResult(self.nodal_displacement()[self._node_of_vertex], wrench[:, :3], wrench[:, 3:], record,
                           poses)

    def _frame_records(self, ind) -> tuple[float, np.ndarray, float]:
        """(friction's lag residual (N), the wrench ((indenters, 6): N, N mm), the smallest det F) at the frame's
        solution: launched together, then read, so that the first read waits for all of them and the others for
        nothing."""
        lagged = self._launch_friction_lag_residual(ind)
        self._launch_wrench(ind)
        self._launch_min_det(self.u)
        return (self._read_free_norm() if lagged else 0.0), self._read_wrench(), self._read_min_det()

    def snapshot(self):
        """Opaque copy of the solver state (to try a frame and go back, e.g. press-to-force)."""
        return (wp.clone(self.u.dof_values), wp.clone(self._contact_state.stick_next), [P.copy() for P in self._poses],
                self.frame_index, self._increment)

    def restore(self, state) -> None:
        dofs, stick, poses, frame, increment = state
        wp.copy(self.u.dof_values, dofs)
        wp.copy(self._contact_state.stick_next, stick)
        self._poses, self.frame_index, self._increment = [P.copy() for P in poses], frame, increment

    @property
    def poses(self) -> list[np.ndarray]:
        return [P.copy() for P in self._poses]

    def nodal_displacement(self) -> np.ndarray:
        return self.u.dof_values.numpy()
