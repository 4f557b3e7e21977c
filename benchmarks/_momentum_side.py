"""Momentum's half of ``benchmarks/peer_momentum.py``: run under the Python that has ``pymomentum-cpu`` (3.12+).

    PYTHON _momentum_side.py PROBLEM.npz RESULT.npz

Reads the shared problem (skeleton, markers, initial parameters, solver limits), builds a Momentum character with
the same tree and rest offsets (one ball joint per segment as Euler angles, a free root), poses every frame with
``pymomentum.solver.solve_ik`` (Levenberg–Marquardt on position constraints, the frames as one batch), and writes
the joint positions with the solve's wall time. Nothing here imports bcmocap.
"""

from __future__ import annotations

import sys
import time

import numpy as np


def main(problem_path: str, result_path: str) -> int:
    import pymomentum.geometry as geometry
    import pymomentum.solver as solver
    import torch

    p = np.load(problem_path)
    cm = 100.0  # Momentum works in centimetres (its solver's thresholds and weights are tuned to them)
    parents, offsets = p["parents"].astype(int), (cm * p["offsets"]).astype(np.float32)
    num_joints = len(parents)
    joints = [geometry.Joint(f"j{k}", int(parents[k]), np.array([0, 0, 0, 1], np.float32), offsets[k])
              for k in range(num_joints)]
    skeleton = geometry.Skeleton(joints)
    # model parameters: the root's translation and rotation, then three rotation angles per other joint
    names = ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    rows = [0, 1, 2, 3, 4, 5]
    for k in range(1, num_joints):
        names += [f"j{k}_rx", f"j{k}_ry", f"j{k}_rz"]
        rows += [7 * k + 3, 7 * k + 4, 7 * k + 5]
    transform = np.zeros((7 * num_joints, len(names)), np.float32)
    transform[rows, np.arange(len(names))] = 1.0
    character = geometry.Character("peer", skeleton, geometry.ParameterTransform(names, skeleton, transform))

    targets = torch.from_numpy((cm * p["targets"]).astype(np.float32))  # (F, M, 3)
    seen = torch.from_numpy(p["seen"].astype(np.float32))  # (F, M)
    frames = targets.shape[0]
    init = np.zeros((frames, len(names)), np.float32)
    init[:, :3] = cm * p["initial_root"] - offsets[0]
    problem = dict(  # the same for every iteration limit
        character=character,
        active_parameters=torch.ones(len(names), dtype=torch.bool),
        model_parameters_init=torch.from_numpy(init),
        active_error_functions=[solver.ErrorFunctionType.Position],
        error_function_weights=torch.ones(frames, 1),
        position_cons_parents=torch.from_numpy(p["marker_segment"].astype(np.int32)),
        position_cons_offsets=torch.from_numpy((cm * p["marker_offsets"]).astype(np.float32)),
        position_cons_weights=seen,
        position_cons_targets=targets,
    )
    out = {}
    for steps in p["max_steps"]:
        options = solver.SolverOptions(max_iter=int(steps), min_iter=1, threshold=float(p["threshold"]), verbose=False)
        kwargs = {**problem, "options": options}
        start = time.perf_counter()
        solver.solve_ik(**kwargs)
        first = time.perf_counter() - start
        seconds = []
        for _ in range(int(p["repeats"])):
            start = time.perf_counter()
            params = solver.solve_ik(**kwargs)
            seconds.append(time.perf_counter() - start)
        state = geometry.model_parameters_to_skeleton_state(character, params.detach().numpy())  # (F, J, 8): xyz, xyzw, s
        state = np.asarray(state, np.float64)
        x, y, z, w = np.moveaxis(state[..., p["marker_segment"], 3:7], -1, 0)  # each marker's joint rotation
        v = cm * p["marker_offsets"]
        t = 2 * np.cross(np.stack([x, y, z], -1), v)
        markers = state[..., p["marker_segment"], :3] + v + w[..., None] * t + np.cross(np.stack([x, y, z], -1), t)
        out[f"joint_positions_{steps}"] = state[..., :3] / cm
        out[f"marker_positions_{steps}"] = markers / cm
        out[f"first_seconds_{steps}"] = first
        out[f"seconds_{steps}"] = np.array(seconds)
    np.savez(result_path, threads=torch.get_num_threads(), **out)
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: PYTHON _momentum_side.py PROBLEM.npz RESULT.npz (see benchmarks/peer_momentum.py)")
    raise SystemExit(main(*sys.argv[1:3]))
