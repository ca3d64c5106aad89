"""The warm start of a quasi-static (sub)step, as a mixin of ``QuasiStaticSolver`` (solver.py): the guess Newton
(newton.py) starts from, and whose contact can give friction's first lag.

Each (sub)step used to start from the last converged state u_prev. It now starts from the lowest-energy guess with
det F > 0 among u_prev, the last increment scaled to this step's pose increment, u_prev carried along by the
indenter's tangential translation (a slide: the dent starts where it will be) and, where an indenter lifts off,
u_prev scaled towards the rest shape (BENCHMARKS.md ``fem_unload_warm_start``). Displacements in mm, gel frame.
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.fem as fem

#: where an indenter moves away from the gel, u_prev scaled by each of these is a warm-start guess (``_warm_start``)
UNLOAD_SCALES = (0.25, 0.5, 0.75)


def lifts_off(step: np.ndarray, tol_mm: float) -> bool:
    """Whether some indenter moves away from the gel (+z, the contact surface faces +z) by more than ``tol_mm`` in the
    pose increment ``step`` (newton.py ``_pose_step``: 6 values per indenter, translation first)."""
    return bool(np.any(step.reshape(-1, 6)[:, 2] > tol_mm))


class WarmStart:
    """The warm start for ``QuasiStaticSolver`` (which provides the fields, energy, det F and penetration)."""

    def _warm_start(self, ind, step: np.ndarray) -> bool:
        """Starts Newton from the lowest-energy guess with det F > 0 among u_prev and

        - u_prev + s du_last: the last converged increment scaled to this step's pose increment
          (s = <step, step_last> / |step_last|^2, clipped to [0, 1]): on a steady press or slide this starts
          Newton next to the solution;
        - u_prev carried along by the indenter's tangential (x, y) translation d, u(X) = u_prev(X - d) (one
          indenter only): the dent moves with the indenter where a slide starts (the step turns from a press,
          so the last increment points the wrong way);
        - u_prev scaled by ``UNLOAD_SCALES`` where an indenter moves away from the gel (+z: the contact surface
          faces +z): on a release the gel springs back towards its rest shape, and neither guess above points
          there (BENCHMARKS.md ``fem_unload_warm_start``).

        True if a guess was taken and the largest penetration there is within 2x the last step's plus
        ``penetration_tol_mm`` (a guess whose contact can serve as friction's first lag)."""
        wp.copy(self.u.dof_values, self.u_prev.dof_values)
        best_e = self._energy(self.u, ind)
        pen_last = self._increment[2] if self._increment is not None else 0.0
        taken = False
        for guess in self._guesses(step):
            wp.copy(self._u_try.dof_values, guess)
            if self._min_det(self._u_try) > 0.0:
                e = self._energy(self._u_try, ind)
                if e < best_e:
                    wp.copy(self.u.dof_values, self._u_try.dof_values)
                    best_e, taken = e, True
        if not taken:
            return False
        self.stats["warm_starts"] += 1
        return self._max_penetration(ind) <= 2.0 * pen_last + self.settings.penetration_tol_mm

    def _guesses(self, step: np.ndarray):
        """The warm start's candidate dof values (see ``_warm_start``)."""
        if self._increment is not None:
            du_last, step_last, _ = self._increment
            norm2 = float(np.dot(step_last, step_last))
            scale = float(np.clip(np.dot(step, step_last) / norm2, 0.0, 1.0)) if norm2 > 0.0 else 0.0
            if scale > 0.0:
                guess = wp.clone(self.u_prev.dof_values)
                fem.linalg.array_axpy(x=du_last, y=guess, alpha=scale)
                yield guess
        shift = np.array([step[0], step[1], 0.0]) if len(self.indenters) == 1 else np.zeros(3)
        if np.linalg.norm(shift) > self.settings.newton_tol_mm:
            yield self._carried(shift)
        if lifts_off(step, self.settings.newton_tol_mm):
            for scale in UNLOAD_SCALES:
                guess = wp.zeros_like(self.u_prev.dof_values)
                fem.linalg.array_axpy(x=self.u_prev.dof_values, y=guess, alpha=scale, beta=0.0)
                yield guess

    def _carried(self, shift: np.ndarray) -> wp.array:
        """Dof values of u_prev(X - shift) (u_prev itself at nodes whose X - shift is outside the gel, and 0 on the
        fixed components), found on the device: each node's X - shift is looked up in the tet mesh's BVH
        (``fem.lookup``; built on first use) and u_prev evaluated there."""
        if self._geo.bvh_id(self.device) == 0:
            self._geo.build_bvh(self.device)
        out = wp.empty_like(self.u_prev.dof_values)
        fem.interpolate(_carried_form, dest=out, at=self._cells, dim=len(out), fields={"u": self.u_prev},
                        values={"nodes": self._node_positions, "shift": wp.vec3d(*shift),
                                "kept": self.u_prev.dof_values, "tol": 1.0e-8})
        values = out.numpy()
        values[self._fixed_nodes] = 0.0
        return wp.array(values, dtype=wp.vec3d, device=self.device)


@fem.integrand
def _carried_form(s: fem.Sample, domain: fem.Domain, u: fem.Field, nodes: wp.array(dtype=wp.vec3d),
                  shift: wp.vec3d, kept: wp.array(dtype=wp.vec3d), tol: wp.float64):
    """u at nodes[i] - shift where that point lies in the gel (within tol mm of where the lookup lands), else
    kept[i]."""
    y = nodes[s.qp_index] - shift
    found = fem.lookup(domain, y)
    value = kept[s.qp_index]
    if found.element_index != fem.NULL_ELEMENT_INDEX:
        if wp.length(fem.position(domain, found) - y) <= tol:
            value = u(found)
    return value
