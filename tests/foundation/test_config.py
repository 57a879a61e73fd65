"""Robot, payload and truth files: shipped ones load; malformed ones fail with one exact line."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np
import pytest

from drivegain.config import load_payload, load_robot, load_truth, resource_path
from drivegain.config._toml import Table
from drivegain.config.schema import (
    SettingError,
    derived,
    load_table,
    setting,
)
from drivegain.errors import ConfigError

TX40 = resource_path("tx40.toml")


def test_tx40_loads_with_paper_values() -> None:
    robot = load_robot(TX40)
    assert robot.n == 6
    assert robot.joint_names == ["j1", "j2", "j3", "j4", "j5", "j6"]
    np.testing.assert_allclose(robot.gear_ratios, [32, 32, 45, -48, 45, 32])
    np.testing.assert_allclose(robot.apriori_gains, [32.96, 32.96, 25.65, -11.52, 18.48, 7.68])
    # Table 1 of the paper: d3, r3, r4 and the offsets of joints 2 and 3.
    mdh = [j.mdh for j in robot.joints]
    assert mdh[2] is not None and mdh[3] is not None and mdh[1] is not None
    assert (mdh[2].d, mdh[2].r, mdh[3].r) == (0.225, 0.035, 0.225)
    assert mdh[1].theta_offset == pytest.approx(-np.pi / 2)
    assert mdh[2].theta_offset == pytest.approx(np.pi / 2)
    # Manual: +133.5 / -120 deg on joint 5, 700 deg/s on joint 6.
    assert np.degrees(robot.joints[4].position_limits[1]) == pytest.approx(133.5)
    assert np.degrees(robot.joints[5].velocity_limit) == pytest.approx(700.0)
    k = robot.transmission()
    assert k[5, 4] == 32.0 and k[5, 5] == 32.0 and k[4, 5] == 0.0


def test_shipped_payloads_and_truth_load() -> None:
    big = load_payload(resource_path("payloads/calibrated-4590g.toml"), n_links=6)
    small = load_payload(resource_path("payloads/validation-1686g.toml"), n_links=6)
    assert big.mass == 4.59 and small.mass == 1.686
    assert big.known == ("M",)
    truth = load_truth(resource_path("sim/tx40-truth.toml"), n_links=6)
    np.testing.assert_allclose(truth.gains, [33.7, 32.2, 24.1, -8.80, 16.50, 6.82])
    assert (truth.fvm, truth.fcm) == (0.8, 1.6)


def _mutate(tmp_path: Path, source: Path, old: str, new: str, count: int = 1) -> Path:
    text = source.read_text()
    assert old in text, old
    out = tmp_path / source.name
    out.write_text(text.replace(old, new, count))
    return out


ROBOT_CASES = [
    # (description, old text, new text, expected message after "<file>: ")
    ("missing key", "gear_ratio = 32.0\n", "", "key 'joint[0].gear_ratio': missing"),
    (
        "mistyped key",
        "velocity_limit = 5.009094953223726          # 287 deg/s\nacceleration_limit = 12.0",
        "velocity_limt = 5.0\nacceleration_limit = 12.0",
        "key 'joint[0].velocity_limt': unknown key (expected one of acceleration_limit, "
        "apriori_gain, encoder_counts, gear_ratio, jerk_limit, mdh, name, node_id, "
        "position_limits, rated_current, velocity_limit)",
    ),
    (
        "wrong array length",
        "gravity = [0.0, 0.0, -9.81]",
        "gravity = [0.0, -9.81]",
        "key 'robot.gravity': expected 3 values, got 2",
    ),
    (
        "string for number",
        "gear_ratio = 32.0",
        'gear_ratio = "32"',
        "key 'joint[0].gear_ratio': expected a number, got '32'",
    ),
    (
        "negative velocity limit",
        "velocity_limit = 5.009094953223726",
        "velocity_limit = -5.0",
        "key 'joint[0].velocity_limit': must be > 0, got -5.0",
    ),
    (
        "inverted position limits",
        "position_limits = [-3.141592653589793, 3.141592653589793]",
        "position_limits = [3.0, -3.0]",
        "key 'joint[0].position_limits': lower must be below upper, got [3.0, -3.0]",
    ),
    (
        "bad friction form",
        'wrist_friction = "physical"',
        'wrist_friction = "magic"',
        "key 'robot.wrist_friction': must be one of physical, paper, got 'magic'",
    ),
    (
        "node id out of range",
        "node_id = 1\n",
        "node_id = 200\n",
        "key 'joint[0].node_id': CANopen node id must be 1..127, got 200",
    ),
    (
        "duplicate node id",
        "node_id = 2\n",
        "node_id = 1\n",
        "key 'joint[1].node_id': duplicate node_id 1",
    ),
    (
        "coupling to a missing joint",
        "joint = 5\n",
        "joint = 9\n",
        "key 'coupling[0].joint': must be a joint number 1..6, got 9",
    ),
    ("not TOML", "[robot]", "[robot", None),
]


@pytest.mark.parametrize(
    ("what", "old", "new", "message"), ROBOT_CASES, ids=[c[0] for c in ROBOT_CASES]
)
def test_malformed_robot_file(
    tmp_path: Path, what: str, old: str, new: str, message: str | None
) -> None:
    bad = _mutate(tmp_path, TX40, old, new)
    with pytest.raises(ConfigError) as info:
        load_robot(bad)
    text = str(info.value)
    assert "\n" not in text
    if message is None:
        assert re.match(rf"{re.escape(str(bad))}: not valid TOML \(", text)
    else:
        assert text == f"{bad}: {message}"


PAYLOAD = resource_path("payloads/calibrated-4590g.toml")
PAYLOAD_CASES = [
    ("zero mass", "mass = 4.59", "mass = 0.0", "key 'payload.mass': must be > 0, got 0.0"),
    (
        "not positive definite",
        "inertia = [0.064, -0.018, 0.026, 0.064, 0.026, 0.044]",
        "inertia = [0.01, -0.018, 0.026, 0.064, 0.026, 0.044]",
        "key 'payload.inertia': inertia about the centre of mass is not positive definite",
    ),
    (
        "triangle inequality",
        "inertia = [0.064, -0.018, 0.026, 0.064, 0.026, 0.044]",
        "inertia = [0.064, -0.018, 0.026, 0.064, 0.026, 0.07]",
        "key 'payload.inertia': principal moments about the centre of mass violate the "
        "triangle inequality",
    ),
    (
        "wrong first moment length",
        "first_moment = [-0.29, -0.29, 0.41]",
        "first_moment = [-0.29, -0.29]",
        "key 'payload.first_moment': expected 3 values, got 2",
    ),
    (
        "unknown known parameter",
        'known = ["mass"]',
        'known = ["weight"]',
        "key 'payload.known': unknown parameter 'weight' (use mass, MX.., XX..)",
    ),
    (
        "link beyond the robot",
        "link = 6",
        "link = 7",
        "key 'payload.link': the robot has 6 links, got 7",
    ),
]


@pytest.mark.parametrize(
    ("what", "old", "new", "message"), PAYLOAD_CASES, ids=[c[0] for c in PAYLOAD_CASES]
)
def test_malformed_payload_file(
    tmp_path: Path, what: str, old: str, new: str, message: str
) -> None:
    bad = _mutate(tmp_path, PAYLOAD, old, new)
    with pytest.raises(ConfigError) as info:
        load_payload(bad, n_links=6)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{bad}: {message}")


def test_truth_rejects_non_physical_link(tmp_path: Path) -> None:
    bad = _mutate(tmp_path, resource_path("sim/tx40-truth.toml"), "mass = 8.61", "mass = -1.0")
    with pytest.raises(ConfigError, match=r"key 'link\[0\]\.mass': must be > 0, got -1.0"):
        load_truth(bad)


def test_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_robot(tmp_path / "nope.toml")
    assert str(info.value) == f"{tmp_path / 'nope.toml'}: file not found"


# --- the declarative table mechanism ------------------------------------------------------------


class Mode(StrEnum):
    FAST = "fast"
    SLOW = "slow"


@dataclass(frozen=True)
class Inner:
    gain: float = field(default=1.0, metadata=setting(nonzero=True, doc="a gain"))


@dataclass(frozen=True)
class Example:
    period_s: float = field(
        metadata=setting(
            unit="s", gt=0.0, le=0.1, message="must be at most 0.1 s, got {value}", doc="period"
        )
    )
    count: int = field(default=3, metadata=setting(ge=1, doc="how many"))
    mode: Mode = field(default=Mode.FAST, metadata=setting(doc="speed"))
    label: str | None = field(default=None, metadata=setting(key="name", doc="a label"))
    values: tuple[float, ...] = field(default=(), metadata=setting(unit="rad", doc="values"))
    inner: tuple[Inner, ...] = field(default=(), metadata=setting(key="item", doc="items"))
    source: str = field(default="", metadata=derived(doc="given by the caller"))

    def __post_init__(self) -> None:
        if self.count > 10 and self.mode == Mode.SLOW:
            raise SettingError("count", "at most 10 when slow")


def _load(data: dict, **given) -> Example:
    return load_table(Example, Table(data, "x.toml", "ex"), **given)


def test_load_table_reads_defaults_types_and_derived_fields() -> None:
    cfg = _load({"period_s": 0.01}, source="here")
    assert cfg == Example(period_s=0.01, source="here")
    cfg = _load(
        {"period_s": 0.1, "count": 4, "mode": "slow", "name": "a", "values": [1, 2.5]},
    )
    assert (cfg.count, cfg.mode, cfg.label, cfg.values) == (4, Mode.SLOW, "a", (1.0, 2.5))
    assert isinstance(cfg.mode, Mode)
    cfg = _load({"period_s": 0.01, "item": [{"gain": 2.0}, {}]})
    assert cfg.inner == (Inner(2.0), Inner())


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({}, "key 'ex.period_s': missing"),
        ({"period_s": "1"}, "key 'ex.period_s': expected a number, got '1'"),
        ({"period_s": 0}, "key 'ex.period_s': must be > 0, got 0.0"),
        ({"period_s": 0.5}, "key 'ex.period_s': must be at most 0.1 s, got 0.5"),
        ({"period_s": 0.01, "count": 0}, "key 'ex.count': must be >= 1, got 0"),
        ({"period_s": 0.01, "count": True}, "key 'ex.count': expected an integer, got True"),
        ({"period_s": 0.01, "mode": "x"}, "key 'ex.mode': must be one of fast, slow, got 'x'"),
        ({"period_s": 0.01, "label": "a"}, "key 'ex.label': unknown key (expected one of count, "),
        ({"period_s": 0.01, "source": "a"}, "key 'ex.source': unknown key"),
        ({"period_s": 0.01, "item": [{"gain": 0.0}]}, "key 'ex.item[0].gain': must not be zero"),
        ({"period_s": 0.01, "count": 11, "mode": "slow"}, "key 'ex.count': at most 10 when slow"),
    ],
)
def test_load_table_errors_are_one_line_naming_file_and_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        _load(data)
    text = str(info.value)
    assert text.startswith(f"x.toml: {message}") and "\n" not in text


@pytest.mark.parametrize(
    ("file", "old", "new", "key"),
    [
        ("tx40.toml", "velocity_limit = 5.009094953223726", "velocity_limit = 1e308", "velocity"),
        ("tx40.toml", "velocity_limit = 5.009094953223726", "velocity_limit = nan", "velocity"),
        ("payloads/calibrated-4590g.toml", "mass = 4.59", "mass = 1e300", "payload.mass"),
        ("payloads/calibrated-4590g.toml", "mass = 4.59", "mass = inf", "payload.mass"),
    ],
    ids=["velocity-1e308", "velocity-nan", "mass-1e300", "mass-inf"],
)
def test_physically_impossible_values_are_refused_at_load(
    tmp_path: Path, file: str, old: str, new: str, key: str
) -> None:
    text = resource_path(file).read_text()
    assert old in text
    bad = tmp_path / Path(file).name
    bad.write_text(text.replace(old, new, 1))
    loader = load_robot if file == "tx40.toml" else load_payload
    with pytest.raises(ConfigError) as exc:
        loader(bad)
    msg = str(exc.value)
    assert str(bad) in msg and key in msg and "must be finite" in msg
    assert "\n" not in msg


# --- issue 16, item 6: what identification needs of a robot file ----------------------------


def _strip(tmp_path: Path, keys: tuple[str, ...]) -> Path:
    """The TX-40 file without the lines setting ``keys``."""
    lines = [ln for ln in TX40.read_text().splitlines() if ln.split("=")[0].strip() not in keys]
    out = tmp_path / "bare.toml"
    out.write_text("\n".join(lines) + "\n")
    return out


def test_identification_reads_a_robot_file_without_acquisition_keys(tmp_path: Path) -> None:
    from drivegain.config.robot import ACQUISITION_KEYS

    bare = _strip(tmp_path, (*ACQUISITION_KEYS, "apriori_gain"))
    full = load_robot(TX40)
    robot = load_robot(bare, acquisition=False)
    assert robot.joint_names == full.joint_names
    assert [j.mdh for j in robot.joints] == [j.mdh for j in full.joints]
    np.testing.assert_array_equal(robot.gear_ratios, full.gear_ratios)
    np.testing.assert_array_equal(robot.transmission(), full.transmission())
    # A priori gains omitted: the gear ratios (signed).
    np.testing.assert_array_equal(robot.apriori_gains, [32, 32, 45, -48, 45, 32])
    assert robot.apriori_from_gear_ratio == tuple(full.joint_names)
    assert len(robot.missing) == 6 * len(ACQUISITION_KEYS)
    assert "joint[0].encoder_counts" in robot.missing
    # Acquisition still requires them, with one clear line.
    with pytest.raises(ConfigError) as info:
        load_robot(bare)
    assert str(info.value) == f"{bare}: key 'joint[0].acceleration_limit': missing"


def test_zero_apriori_gain_is_the_gear_ratio_not_an_error(tmp_path: Path) -> None:
    path = _mutate(tmp_path, TX40, "apriori_gain = 32.96\n", "apriori_gain = 0.0\n")
    for acquisition in (True, False):
        robot = load_robot(path, acquisition=acquisition)
        assert robot.apriori_gains[0] == robot.gear_ratios[0] == 32.0
        assert robot.apriori_gains[1] == 32.96
        assert robot.apriori_from_gear_ratio == ("j1",)


def test_shipped_robot_is_the_same_for_acquisition_and_identification() -> None:
    a, b = load_robot(TX40), load_robot(TX40, acquisition=False)
    assert a.joints == b.joints and b.missing == () and b.apriori_from_gear_ratio == ()
