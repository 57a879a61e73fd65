"""A simulated fleet: run logs of several robots over several campaigns, and their campaign file.

For tests, benchmarks and trying ``drivegain batch`` without a plant. Every robot is a TX-40
(the shipped model and simulation truth) whose drive gains differ from the nominal ones by a
fixed, robot-specific amount (unit-to-unit spread); a :class:`Change` alters one robot's gain
or friction from a given campaign on. Each robot and campaign gets an unloaded run and a run
with the shipped calibrated payload, simulated by inverse dynamics
(:func:`drivegain.identify.synth.simulate_run`) with torque noise and encoder quantisation,
new noise for every run, so the identified σ are those of real repeated campaigns.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config.robot import WristFriction
from drivegain.config.truth import Truth
from drivegain.dynamics.model import build_model
from drivegain.errors import InputError
from drivegain.formats.log import run_metadata
from drivegain.formats.logwriter import write_run
from drivegain.identify.blas import limited_blas_threads
from drivegain.identify.columns import bases_for_forms
from drivegain.identify.synth import exciting_sum_of_sines, simulate_run

ROBOT = "tx40"
PAYLOAD = "payloads/calibrated-4590g.toml"
TRUTH = "sim/tx40-truth.toml"
#: Excitation of the simulated runs: base frequency, Hz, and harmonics.
BASE_HZ = 0.2
HARMONICS = 5
#: Noise of docs/model.md: joint-torque noise, N·m, and the encoder quantum at the joint, rad.
TORQUE_NOISE = 0.05
QUANTUM = float(np.deg2rad(1e-3))
#: Unit-to-unit spread of the drive gains (relative standard deviation).
GAIN_SPREAD = 0.02


@dataclass(frozen=True)
class Change:
    """A change of one robot from one campaign on.

    Attributes
    ----------
    robot_id, campaign
        The robot, and the first campaign that has the change.
    kind
        ``gain`` (drive gain, N·m/A) or ``viscous`` (viscous friction Fv, N·m·s/rad).
    joint
        Joint number, 1-based.
    factor
        Multiplier of the parameter (1.03: +3 %).
    """

    robot_id: str
    campaign: str
    kind: str
    joint: int
    factor: float

    def __post_init__(self) -> None:
        if self.kind not in ("gain", "viscous"):
            raise InputError(f"must be gain or viscous, got {self.kind!r}", key="kind")


def _truth_for(
    base: Truth,
    gains: np.ndarray,
    rid: str,
    order: Sequence[str],
    campaign: str,
    changes: Sequence[Change],
) -> Truth:
    links = list(base.links)
    g = gains.copy()
    for c in changes:
        if c.robot_id != rid or order.index(campaign) < order.index(c.campaign):
            continue
        j = c.joint - 1
        if c.kind == "gain":
            g[j] *= c.factor
        else:
            links[j] = replace(links[j], Fv=links[j].Fv * c.factor)
    return replace(base, links=tuple(links), gains=g)


def write_fleet(
    folder: Path,
    robots: Sequence[str],
    campaigns: Sequence[tuple[str, str]],
    changes: Sequence[Change] = (),
    *,
    seconds: float = 20.0,
    rate_hz: float = 100.0,
    seed: int = 0,
    batch: dict[str, object] | None = None,
) -> Path:
    """Write the logs of ``robots`` × ``campaigns`` below ``folder`` and a campaign file.

    Parameters
    ----------
    folder
        Output folder: ``logs/ROBOT_ID/CAMPAIGN/{unloaded,loaded}.mcap`` and ``campaign.toml``.
    robots
        Robot ids.
    campaigns
        ``(name, ISO date)`` in chronological order.
    changes
        Changes of some robots from some campaign on.
    seconds, rate_hz
        Length (s) and sample rate (Hz) of each run.
    seed
        Seed of the excitations, gain spread and noise.
    batch
        Extra keys of the file's ``[batch]`` table (default: ``out = "results"``).

    Returns
    -------
    Path
        The campaign file.
    """
    rng = np.random.default_rng(seed)
    robot = load_robot(resource_path(f"{ROBOT}.toml"))
    model = build_model(robot)
    truth = load_truth(resource_path(TRUTH))
    payload = load_payload(resource_path(PAYLOAD))
    with limited_blas_threads(1):
        bases = bases_for_forms(model)
        excitations = [
            exciting_sum_of_sines(
                model,
                rng,
                base_frequency_hz=BASE_HZ,
                harmonics=HARMONICS,
                candidates=4,
                base=bases[WristFriction.PHYSICAL],
            )
            for _ in range(2)
        ]
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    motion = [e.evaluate(t)[:3] for e in excitations]
    order = [name for name, _ in campaigns]
    gains = {rid: truth.gains * (1 + GAIN_SPREAD * rng.standard_normal(robot.n)) for rid in robots}
    lines = ["[batch]"]
    for k, v in {"out": "results", **(batch or {})}.items():
        lines.append(f"{k} = {json.dumps(v)}")
    lines += [
        "",
        "[defaults]",
        f'robot = "{ROBOT}"',
        f"payload = {json.dumps(str(resource_path(PAYLOAD)))}",
    ]
    for name, date in campaigns:
        lines += ["", "[[campaign]]", f'name = "{name}"', f"date = {date}"]
        for rid in robots:
            tr = _truth_for(truth, gains[rid], rid, order, name, changes)
            runs = {}
            for label, pay, (q, qd, qdd), exc in zip(
                ("unloaded", "loaded"), (None, payload), motion, excitations, strict=True
            ):
                sim = simulate_run(
                    model,
                    tr,
                    q,
                    qd,
                    qdd,
                    payload=pay,
                    torque_noise=TORQUE_NOISE,
                    quantum=QUANTUM,
                    rng=rng,
                )
                fourier = {
                    "base_frequency_hz": exc.base_frequency_hz,
                    "q0": exc.q0.tolist(),
                    "a": exc.a.tolist(),
                    "b": exc.b.tolist(),
                }
                meta = run_metadata(
                    robot, label, pay, 1.0 / rate_hz, f"{date}T08:00:00.000Z", {"robot_id": rid}
                )
                path = folder / "logs" / rid / name / f"{label}.mcap"
                path.parent.mkdir(parents=True, exist_ok=True)
                att = [
                    (
                        "trajectory.json",
                        "application/json",
                        json.dumps({"format_version": 1, "fourier": fourier}).encode(),
                    )
                ]
                write_run(path, meta, t, sim.q, sim.current_reference, attachments=att)
                runs[label] = path.relative_to(folder).as_posix()
            lines += [
                "",
                "[[campaign.robot]]",
                f'id = "{rid}"',
                f'unloaded = "{runs["unloaded"]}"',
                f'loaded = "{runs["loaded"]}"',
            ]
    path = folder / "campaign.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
