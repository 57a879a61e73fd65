"""``drivegain export urdf``: the consistent identification as a URDF and a controller TOML.

The URDF holds the identified mass, centre of mass and inertia of every link. Its link frames
are the model's joint frames: for a robot described by MDH rows, each URDF joint's origin is the
MDH placement of Rx(α)·Tx(d)·Rz(θ_offset)·Tz(r) (so the URDF joint angle is the controller's q,
and the link frames are the MDH frames); a robot described by a URDF gets its own file back with
the inertials replaced (:func:`rewrite_urdf`).
Parameters at the frame origin (Khalil's XX..ZZ, MX..MZ, M, tensor elements) become URDF's
``<inertial>``: COM ``c = h/m`` and the inertia about the COM, ``I_c = I_O − m(|c|²·1 − c cᵀ)``,
in axes parallel to the link frame (URDF's ixy is the tensor element, as Khalil's XY).

What a URDF cannot hold goes to the controller TOML: drive gains, rotor inertias (the diagonal
as Pinocchio ``armature``, and the coupled-wrist cross terms), viscous and Coulomb friction,
torque offsets, the coupled-motor friction and its form. :func:`exported_torque` evaluates that
pair the way a controller would: ``pin.rnea`` plus the terms of the TOML.
"""

from __future__ import annotations

import argparse
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from drivegain.config.robot import Robot, load_robot
from drivegain.dynamics.model import RobotModel, build_model
from drivegain.dynamics.params import N_PER_JOINT, standard_names
from drivegain.errors import DataError, InputError
from drivegain.fileio import check_output, write_atomic


def com_inertia(inertial10: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (m) and 3×3 inertia about it (kg·m²) of one body.

    ``inertial10`` is ``[XX XY XZ YY YZ ZZ MX MY MZ M]`` at the frame origin. A body without
    mass keeps its inertia at the origin and a COM at the origin.
    """
    xx, xy, xz, yy, yz, zz, mx, my, mz, m = (float(v) for v in inertial10)
    i_o = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    if m <= 0.0:
        return 0.0, np.zeros(3), i_o
    c = np.array([mx, my, mz]) / m
    return m, c, i_o - m * (float(c @ c) * np.eye(3) - np.outer(c, c))


def _f(x: float) -> str:
    return repr(float(x))


def _vec(v: np.ndarray) -> str:
    return " ".join(_f(x) for x in v)


def _inertial_xml(inertial10: np.ndarray, indent: str) -> str:
    m, c, i_c = com_inertia(inertial10)
    return (
        f"{indent}<inertial>\n"
        f'{indent}  <origin xyz="{_vec(c)}" rpy="0 0 0"/>\n'
        f'{indent}  <mass value="{_f(m)}"/>\n'
        f'{indent}  <inertia ixx="{_f(i_c[0, 0])}" ixy="{_f(i_c[0, 1])}" ixz="{_f(i_c[0, 2])}" '
        f'iyy="{_f(i_c[1, 1])}" iyz="{_f(i_c[1, 2])}" izz="{_f(i_c[2, 2])}"/>\n'
        f"{indent}</inertial>\n"
    )


def urdf_text(model: RobotModel, chi: np.ndarray) -> str:
    """A URDF of the serial chain with the inertial parameters of ``chi`` (standard vector).

    Links ``base_link``, ``link1``..``linkn``; joints keep the robot's names, limits and
    effort (a priori gain × rated current) and velocity limits.
    """
    import pinocchio as pin

    robot = model.robot
    parts = [f'<?xml version="1.0"?>\n<robot name={quoteattr(robot.name)}>\n']
    parts.append('  <link name="base_link"/>\n')
    for j, joint in enumerate(robot.joints):
        block = chi[N_PER_JOINT * j : N_PER_JOINT * j + 10]
        parts.append(f'  <link name="link{j + 1}">\n{_inertial_xml(block, "    ")}  </link>\n')
        parent = "base_link" if j == 0 else f"link{j}"
        rpy = pin.rpy.matrixToRpy(model.rotations[j])
        effort = abs(joint.apriori_gain) * joint.rated_current
        parts.append(
            f'  <joint name={quoteattr(joint.name)} type="revolute">\n'
            f'    <parent link="{parent}"/>\n    <child link="link{j + 1}"/>\n'
            f'    <origin xyz="{_vec(model.translations[j])}" rpy="{_vec(rpy)}"/>\n'
            f'    <axis xyz="{_vec(model.axes[j])}"/>\n'
            f'    <limit lower="{_f(joint.position_limits[0])}" '
            f'upper="{_f(joint.position_limits[1])}" effort="{_f(effort)}" '
            f'velocity="{_f(joint.velocity_limit)}"/>\n'
            "  </joint>\n"
        )
    parts.append("</robot>\n")
    return "".join(parts)


def rewrite_urdf(path: Path, model: RobotModel, chi: np.ndarray) -> str:
    """The robot's own URDF with the identified inertials (visuals, collisions, limits kept).

    The child link of each moving joint gets the identified body; links fixed to a moving link
    lose their ``<inertial>`` (Pinocchio merges them into that body, which the identification
    saw as one).

    Raises
    ------
    DataError
        The URDF cannot be read or lacks a joint of the model.
    """
    import xml.etree.ElementTree as ET

    try:
        tree = ET.parse(path)
    except (OSError, ET.ParseError) as exc:
        raise DataError(f"cannot read the URDF ({exc})", file=path) from None
    root = tree.getroot()
    links = {el.get("name"): el for el in root.findall("link")}
    joints = {el.get("name"): el for el in root.findall("joint")}
    children: dict[str, list[tuple[str, str]]] = {}
    for el in joints.values():
        parent, child = el.find("parent"), el.find("child")
        if parent is not None and child is not None:
            children.setdefault(str(parent.get("link")), []).append(
                (str(el.get("type")), str(child.get("link")))
            )
    for j, name in enumerate(model.pin_model.names[1:]):
        joint_el = joints.get(name)
        child = joint_el.find("child") if joint_el is not None else None
        if child is None or child.get("link") not in links:
            raise DataError(f"no joint {name!r} with a child link", file=path)
        link = links[str(child.get("link"))]
        for old in link.findall("inertial"):
            link.remove(old)
        block = chi[N_PER_JOINT * j : N_PER_JOINT * j + 10]
        link.insert(0, ET.fromstring(_inertial_xml(block, "")))
        stack = [c for t, c in children.get(str(child.get("link")), []) if t == "fixed"]
        while stack:
            fixed = links[stack.pop()]
            for old in fixed.findall("inertial"):
                fixed.remove(old)
            stack += [c for t, c in children.get(str(fixed.get("name")), []) if t == "fixed"]
    ET.indent(tree)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


@dataclass(frozen=True)
class Controller:
    """Drive gains and the joint-space terms a URDF cannot hold (the controller TOML).

    Attributes
    ----------
    gains
        Drive gains, N·m/A, joint side.
    armature
        Rotor inertia Ia_j seen at joint j (diagonal), kg·m².
    viscous, coulomb, offset
        Fv_j (N·m·s/rad), Fc_j (N·m), torque offset (N·m).
    couplings
        Per coupled motor: (motor, joint) 0-based, cross rotor inertia Ia_motor (kg·m²),
        fvm (N·m·s/rad), fcm (N·m).
    friction_form
        Coupled-wrist friction form (``physical`` or ``paper``, docs/model.md).
    """

    gains: np.ndarray
    armature: np.ndarray
    viscous: np.ndarray
    coulomb: np.ndarray
    offset: np.ndarray
    couplings: list[tuple[int, int, float, float, float]]
    friction_form: str


def controller_from_report(robot: Robot, doc: dict[str, Any]) -> tuple[np.ndarray, Controller]:
    """Standard parameters and controller terms from a report's ``consistent`` section.

    Raises
    ------
    DataError
        No ``consistent`` section, or its parameters do not belong to ``robot``.
    """
    sec = doc.get("consistent") if isinstance(doc, dict) else None
    if not isinstance(sec, dict):
        raise DataError("no 'consistent' section: run 'drivegain identify --consistent'")
    names = standard_names(robot)
    if sec.get("standard_names") != names:
        raise DataError("its standard parameters are not those of this robot", key="consistent")
    try:
        chi = np.array(sec["standard"], dtype=float)
        gains = np.array(sec["gains"]["values"], dtype=float)
        form = str(sec["friction"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"malformed 'consistent' section ({exc})", key="consistent") from None
    if not np.all(np.isfinite(chi)) or gains.shape != (robot.n,):
        raise DataError("non-finite parameters or wrong gain count", key="consistent")
    blocks = chi[: N_PER_JOINT * robot.n].reshape(robot.n, N_PER_JOINT)
    couplings = []
    for k, c in enumerate(robot.couplings):
        off = N_PER_JOINT * robot.n + 2 * k
        ia_m = float(blocks[c.motor, 10])
        couplings.append((c.motor, c.joint, ia_m, float(chi[off]), float(chi[off + 1])))
    ctrl = Controller(
        gains=gains,
        armature=blocks[:, 10].copy(),
        viscous=blocks[:, 11].copy(),
        coulomb=blocks[:, 12].copy(),
        offset=blocks[:, 13].copy(),
        couplings=couplings,
        friction_form=form,
    )
    return chi, ctrl


def controller_toml(robot: Robot, ctrl: Controller, urdf_name: str, source: str) -> str:
    """The controller TOML (SI units, joint side)."""
    lines = [
        f"# Written by drivegain export urdf from {source}: drive gains and the joint-space",
        "# terms of the identified model that a URDF cannot hold. Joint torque of the model:",
        "# rnea(URDF, armature = [joint].armature) + coupled armature + friction + offset.",
        "[robot]",
        f"name = {json.dumps(robot.name)}",
        f"urdf = {json.dumps(urdf_name)}",
        f"friction_form = {json.dumps(ctrl.friction_form)}",
        f"gravity = [{', '.join(_f(g) for g in robot.gravity)}]",
    ]
    for j, name in enumerate(robot.joint_names):
        lines += [
            "",
            "[[joint]]",
            f"name = {json.dumps(name)}",
            f"gain = {_f(ctrl.gains[j])}  # N·m/A",
            f"gear_ratio = {_f(robot.gear_ratios[j])}",
            f"armature = {_f(ctrl.armature[j])}  # kg·m²",
            f"viscous = {_f(ctrl.viscous[j])}  # N·m·s/rad",
            f"coulomb = {_f(ctrl.coulomb[j])}  # N·m",
            f"offset = {_f(ctrl.offset[j])}  # N·m",
        ]
    for motor, joint, ia, fvm, fcm in ctrl.couplings:
        lines += [
            "",
            "[[coupling]]  # motor turns with q_joint + q_motor (1-based numbers)",
            f"motor = {motor + 1}",
            f"joint = {joint + 1}",
            f"armature = {_f(ia)}  # kg·m², cross term between the two joints",
            f"viscous = {_f(fvm)}  # N·m·s/rad",
            f"coulomb = {_f(fcm)}  # N·m",
        ]
    return "\n".join(lines) + "\n"


def read_controller(path: Path) -> Controller:
    """Read a controller TOML written by :func:`controller_toml`."""
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    js = doc["joint"]
    return Controller(
        gains=np.array([j["gain"] for j in js], dtype=float),
        armature=np.array([j["armature"] for j in js], dtype=float),
        viscous=np.array([j["viscous"] for j in js], dtype=float),
        coulomb=np.array([j["coulomb"] for j in js], dtype=float),
        offset=np.array([j["offset"] for j in js], dtype=float),
        couplings=[
            (c["motor"] - 1, c["joint"] - 1, c["armature"], c["viscous"], c["coulomb"])
            for c in doc.get("coupling", [])
        ],
        friction_form=doc["robot"]["friction_form"],
    )


def load_exported(urdf: Path, controller: Path) -> tuple[Any, Controller]:
    """The Pinocchio model of an exported URDF (gravity and armature set) and its controller."""
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(urdf))
    ctrl = read_controller(controller)
    grav = tomllib.loads(controller.read_text(encoding="utf-8"))["robot"]["gravity"]
    model.gravity.linear = np.array(grav, dtype=float)
    model.armature = ctrl.armature.copy()
    return model, ctrl


def exported_torque(
    model: Any, ctrl: Controller, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
) -> np.ndarray:
    """Joint torques (N·m, (N, n)) of an exported model along a trajectory (rad, rad/s, rad/s²).

    ``pin.rnea`` (rigid bodies and diagonal armature) plus the coupled-motor cross inertia,
    viscous and Coulomb friction, offsets and coupled-motor friction (docs/model.md).
    """
    import pinocchio as pin

    data = model.createData()
    tau = np.array(
        [pin.rnea(model, data, a, b, c) for a, b, c in zip(q, qd, qdd, strict=True)]
    ).reshape(q.shape)
    tau += ctrl.viscous * qd + ctrl.coulomb * np.sign(qd) + ctrl.offset
    for motor, joint, ia, fvm, fcm in ctrl.couplings:
        s_sum = np.sign(qd[:, joint] + qd[:, motor])
        tau[:, joint] += ia * qdd[:, motor] + fvm * qd[:, motor]
        tau[:, motor] += ia * qdd[:, joint] + fvm * qd[:, joint]
        if ctrl.friction_form == "paper":
            s_m = np.sign(qd[:, motor])
            tau[:, joint] += fcm * s_m
            tau[:, motor] += fcm * (s_sum - s_m)
        else:
            tau[:, joint] += fcm * s_sum
            tau[:, motor] += fcm * s_sum
    return tau


def export_urdf(report: Path, robot_path: Path, out: Path, controller: Path | None) -> Path:
    """Write the URDF and the controller TOML of ``report`` for the robot; returns the TOML path.

    Raises
    ------
    InputError
        Unreadable report or robot file.
    DataError
        The report has no usable ``consistent`` section.
    """
    robot = load_robot(robot_path)
    try:
        doc = json.loads(report.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(
            f"not a readable JSON report ({exc})", file=report, key="--report"
        ) from None
    try:
        chi, ctrl = controller_from_report(robot, doc)
    except DataError as exc:
        raise DataError(exc.message, file=report, key=exc.key) from None
    if controller is None:
        controller = check_output(out.with_suffix(".controller.toml"), overwrite=True)
    model = build_model(robot)
    text = urdf_text(model, chi) if robot.urdf is None else rewrite_urdf(robot.urdf, model, chi)
    write_atomic(out, text.encode())
    write_atomic(controller, controller_toml(robot, ctrl, out.name, report.name).encode())
    return controller


def export_urdf_command(args: argparse.Namespace) -> int:
    """Handler of ``drivegain export urdf`` (options in :mod:`drivegain.cli`)."""
    ctrl = export_urdf(args.report, args.robot, args.out, getattr(args, "controller", None))
    print(f"wrote {args.out} and {ctrl}")
    return 0
