"""Command-line handlers of the identify component (``model info``, ``identify``, ``convert``)."""

from __future__ import annotations

import argparse

import numpy as np

from drivegain.config.robot import load_robot
from drivegain.dynamics.base import base_parameters, random_states
from drivegain.dynamics.model import build_model
from drivegain.dynamics.params import standard_names
from drivegain.dynamics.regressor import stack_joint_major, standard_regressor


def model_info(args: argparse.Namespace) -> int:
    """``drivegain model info``: joints, standard and base parameters, cond(W)."""
    robot = load_robot(args.robot)
    model = build_model(robot)
    print(f"robot: {robot.name} ({robot.n} joints, source {robot.source})")
    print(f"{'joint':<6}{'node':>5}{'ratio':>8}{'gain':>9}  limits (rad)")
    for j in robot.joints:
        lo, hi = j.position_limits
        print(
            f"{j.name:<6}{j.node_id:>5}{j.gear_ratio:>8.1f}{j.apriori_gain:>9.2f}"
            f"  [{lo:+.3f}, {hi:+.3f}]"
        )
    for c in robot.couplings:
        m = robot.joints[c.motor].name
        print(f"coupling: motor of {m} also turns with {robot.joints[c.joint].name}")
    print(f"wrist friction form: {robot.wrist_friction.value}")
    names = standard_names(robot)
    print(f"standard parameters: {len(names)}")
    bp = base_parameters(model, seed=args.seed)
    print(f"base parameters: {bp.n_base}")
    for expr in bp.expressions:
        print(f"  {expr}")
    rng = np.random.default_rng(args.seed + 1)
    w = stack_joint_major(standard_regressor(model, *random_states(model, args.samples, rng)))
    wb = bp.columns(w)
    print(f"cond(W_base) on {args.samples} random states: {np.linalg.cond(wb):.4g}")
    return 0
