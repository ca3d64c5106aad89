"""Per-frame indenter poses from trajectory segments (transtac_sim.config.trajectory), and the frame loop.

Poses are 4x4 local -> gel frame (mm). Within a segment of n frames, frame k (1..n) is at t = k/n of the
segment's motion: translations are linear, rotations turn linearly in angle.

- press (depth): translate along -z until the lowest vertex is ``depth_mm`` below z = thickness.
- press (force): the target normal force ramps linearly to ``force_n``; each frame's depth is found by a
  secant iteration on the indenter's z offset (warm-started from the previous frame), each trial being a
  full quasi-static solve from the previous frame's state.
- slide / rotate / roll / hold / release: as documented in the config module; roll turns about
  z x direction by distance / r, r = height of the reference point above the lowest vertex.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from transtac_sim.config.trajectory import Hold, Press, Release, Roll, Rotate, Slide
from transtac_sim.physics.indenter import RigidIndenter
from transtac_sim.physics.solver import FrameResult, QuasiStaticSolver, SolverDidNotConverge


def _translate(P: np.ndarray, d) -> np.ndarray:
    Q = P.copy()
    Q[:3, 3] += np.asarray(d, dtype=np.float64)
    return Q


def _turn(P: np.ndarray, axis, angle: float) -> np.ndarray:
    Q = P.copy()
    axis = np.asarray(axis, dtype=np.float64)
    Q[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix() @ P[:3, :3]
    return Q


def _direction(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([np.cos(a), np.sin(a), 0.0])


class IndenterTrajectory:
    """Generates one indenter's frames: yields (pose, force target or None) per frame."""

    def __init__(self, indenter: RigidIndenter, start_pose: np.ndarray, segments: list, thickness_mm: float):
        self.indenter = indenter
        self.start_pose = np.asarray(start_pose, dtype=np.float64)
        self.segments = list(segments)
        self.thickness_mm = thickness_mm
        self.frame_count = sum(s.frames for s in self.segments)

    def frames(self) -> Iterator[tuple[np.ndarray, float | None, object]]:
        """Yields (pose, target normal force in N or None, segment). For a force target the pose is the
        frame's starting guess; the caller reports back the pose it settled on through ``send``."""
        P = self.start_pose.copy()
        first_press: np.ndarray | None = None
        for seg in self.segments:
            A = P.copy()
            n = seg.frames
            if isinstance(seg, Press) and first_press is None:
                first_press = A.copy()
            for k in range(1, n + 1):
                t = k / n
                force = None
                if isinstance(seg, Press):
                    if seg.depth_mm is not None:
                        drop = self.indenter.lowest_z(A) - (self.thickness_mm - seg.depth_mm)
                        P = _translate(A, [0.0, 0.0, -t * drop])
                    else:
                        force = t * seg.force_n
                elif isinstance(seg, Hold):
                    P = A
                elif isinstance(seg, Slide):
                    P = _translate(A, t * seg.distance_mm * _direction(seg.direction_deg))
                elif isinstance(seg, Rotate):
                    P = _turn(A, seg.axis, t * np.deg2rad(seg.angle_deg))
                elif isinstance(seg, Roll):
                    d = _direction(seg.direction_deg)
                    radius = A[2, 3] - self.indenter.lowest_z(A)
                    if radius <= 0.0:
                        raise ValueError(f"indenter {self.indenter.name!r}: roll needs its reference point above "
                                         "its lowest point")
                    P = _turn(_translate(A, t * seg.distance_mm * d), np.cross([0.0, 0.0, 1.0], d),
                              t * seg.distance_mm / radius)
                elif isinstance(seg, Release):
                    target = first_press if first_press is not None else self.start_pose
                    P = _translate(A, t * (target[:3, 3] - A[:3, 3]))
                else:
                    raise TypeError(f"unknown trajectory segment {seg!r}")
                settled = yield P, force, seg
                if settled is not None:
                    P = settled
                    yield None  # acknowledge send()


def _solve_for_forces(solver: QuasiStaticSolver, poses: list[np.ndarray], targets: list[float | None],
                      tol_n: float, max_trials: int) -> tuple[FrameResult, list[np.ndarray]]:
    """Secant on each force-targeted indenter's z offset so that -F_z matches its target."""
    state = solver.snapshot()
    which = [i for i, f in enumerate(targets) if f is not None]
    offsets = np.zeros(len(poses))
    history: list[tuple[np.ndarray, np.ndarray]] = []
    touched = np.zeros(len(which), dtype=bool)  # any force in any trial
    for _trial in range(max_trials):
        trial_poses = [_translate(P, [0.0, 0.0, -offsets[i]]) for i, P in enumerate(poses)]
        solver.restore(state)
        result = solver.solve_frame(trial_poses)
        touched |= np.array([np.any(result.forces_n[i] != 0.0) for i in which])
        err = np.array([-result.forces_n[i, 2] - targets[i] for i in which])
        if np.all(np.abs(err) <= tol_n):
            return result, trial_poses
        history.append((offsets[which].copy(), err))
        if len(history) == 1:
            step = np.where(err < 0, 0.05, -0.05)  # mm: first probe
        else:
            (x0, e0), (x1, e1) = history[-2], history[-1]
            slope = np.where(np.abs(e1 - e0) > 1e-12, (e1 - e0) / np.where(x1 != x0, x1 - x0, 1.0), 1.0)
            slope = np.maximum(slope, 1e-6)  # force grows with depth
            step = -e1 / slope
        offsets[which] += step
    solver.restore(state)
    names = ", ".join(solver.indenters[i].name for i in which)
    missed = [solver.indenters[i].name for i, t in zip(which, touched, strict=True) if not t]
    why = (f"; {', '.join(map(repr, missed))} never touched the gel (no force in any trial): check where it is "
           "placed over the gel" if missed else "")
    raise SolverDidNotConverge(
        f"frame {solver.frame_index}: press-to-force for indenter(s) {names} did not reach the target force "
        f"within {tol_n} N after {max_trials} secant trials (last errors {err.tolist()} N){why}"
    )


def simulate_sequence(solver: QuasiStaticSolver, start_poses: list[np.ndarray], segments_per_indenter: list[list],
                      thickness_mm: float, force_tol_n: float = 1e-3, force_rel_tol: float = 0.01,
                      max_force_trials: int = 12) -> Iterator[FrameResult]:
    """Runs the indenters' trajectories together (a shorter one holds its last pose) and yields each frame."""
    trajectories = [IndenterTrajectory(ind, P, segs, thickness_mm)
                    for ind, P, segs in zip(solver.indenters, start_poses, segments_per_indenter, strict=False)]
    solver.start(start_poses)
    gens = [t.frames() for t in trajectories]
    last = [np.asarray(P, dtype=np.float64) for P in start_poses]
    done = [False] * len(gens)
    for _ in range(max(t.frame_count for t in trajectories)):
        poses, targets = [], []
        for i, g in enumerate(gens):
            item = None if done[i] else next(g, None)
            if item is None:
                done[i] = True
                poses.append(last[i])
                targets.append(None)
            else:
                poses.append(item[0])
                targets.append(item[1])
        if any(f is not None for f in targets):
            tol = max(force_tol_n, force_rel_tol * max(f for f in targets if f is not None))
            result, poses = _solve_for_forces(solver, poses, targets, tol, max_force_trials)
            for i, f in enumerate(targets):
                if f is not None:
                    gens[i].send(poses[i])
        else:
            result = solver.solve_frame(poses)
        last = poses
        yield result
