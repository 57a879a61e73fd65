"""CAN bus factory (python-can, from the ``[bus]`` table) and bus-load arithmetic.

The only switch between simulation and hardware is this configuration: ``interface = "virtual"``
for the mocked bus, ``socketcan`` / ``pcan`` / ``kvaser`` / ... for a real one. The virtual bus has
no arbitration and no rate limit, so it cannot show an overloaded bus: :func:`bus_load` computes
the load from the frame layout instead.
"""

from __future__ import annotations

import math
import socket
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import can
import can.util
import canopen

from drivegain.config._toml import Table
from drivegain.config.schema import SettingError, load_table, setting
from drivegain.drivers.clock import Clock
from drivegain.errors import BusError, ConfigError, UsageError

#: Bitrates a CAN 2.0 controller is normally configured for (bit/s).
STANDARD_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)

#: Linux socket option (include/uapi/asm-generic/socket.h); Python's socket module lacks it.
SO_RCVBUFFORCE = 33

#: Seconds the bus reader thread blocks in one ``recv``: bounds how long a disconnect waits.
NOTIFIER_CYCLE_S = 0.05


def _known_interface(name: str) -> str | None:
    if name in can.VALID_INTERFACES:
        return None
    return f"unknown python-can interface {name!r} (e.g. virtual, socketcan, pcan, kvaser)"


def _channel(table: Table, key: str) -> str:
    raw = table.raw(key)
    if isinstance(raw, bool) or not isinstance(raw, str | int):
        raise table.error(key, f"expected a string or an integer, got {raw!r}")
    if not str(raw):
        raise table.error(key, "must not be empty")
    return str(raw)


def _no_reserved(options: dict[str, Any]) -> None:
    reserved = sorted({"interface", "channel", "bitrate"} & set(options))
    if reserved:
        raise SettingError(reserved[0], "set this in [bus] itself, not in [bus.options]")


@dataclass(frozen=True)
class BusConfig:
    """How to open the CAN bus: the ``[bus]`` table.

    Attributes
    ----------
    interface
        python-can interface name (``virtual``, ``socketcan``, ``pcan``, ``kvaser``, ...).
    channel
        Interface channel (``can0``, ``PCAN_USBBUS1``, a virtual channel name, ...); an integer
        in the file is read as its text.
    bitrate
        Nominal bitrate, bit/s, one of :data:`STANDARD_BITRATES` (ignored by the virtual
        interface, used for the bus load).
    receive_buffer
        Size of the kernel's receive buffer of a socketcan socket, bytes. The default 212 992
        bytes lost up to 20 % of a 10 000-frame burst on a loaded machine (and under emulation);
        4 MiB lost none. Set with ``SO_RCVBUFFORCE`` (needs CAP_NET_ADMIN), else ``SO_RCVBUF``
        (capped by ``net.core.rmem_max``). Other interfaces ignore it.
    extra
        Further keyword arguments for :class:`can.Bus` (the ``[bus.options]`` table).
    """

    interface: str = field(
        metadata=setting(
            doc="python-can interface (virtual, socketcan, pcan, ...)", check=_known_interface
        )
    )
    channel: str = field(
        metadata=setting(doc="interface channel (can0, a virtual channel, ...)", parse=_channel)
    )
    bitrate: int = field(
        default=1_000_000,
        metadata=setting(unit="bit/s", ge=1, choices=STANDARD_BITRATES, doc="nominal bitrate"),
    )
    extra: dict[str, Any] = field(
        default_factory=dict,
        metadata=setting(
            key="options",
            check=_no_reserved,
            doc="further keyword arguments of can.Bus (the [bus.options] table)",
        ),
    )
    receive_buffer: int = field(
        default=4 * 1024 * 1024,
        metadata=setting(
            unit="bytes",
            ge=0,
            le=256 * 1024 * 1024,
            doc="socketcan receive buffer (0: the kernel default); a burst fits in it",
        ),
    )


def bus_config_from_table(table: Table) -> BusConfig:
    """Read the ``[bus]`` table of an acquisition TOML (keys: see :class:`BusConfig`).

    Raises
    ------
    ConfigError
        One line naming the file and key at fault.
    """
    return load_table(BusConfig, table)


def bus_config_from_python_can(source: str | None = None) -> BusConfig:
    """The bus python-can's own configuration names, for an acquisition TOML without ``[bus]``:
    ``CAN_INTERFACE`` / ``CAN_CHANNEL`` / ``CAN_BITRATE``, then ``~/.can``, ``/etc/can.conf``
    (python-can's order, :func:`can.util.load_config`).

    Raises
    ------
    ConfigError
        python-can's configuration names no interface or channel, or an unknown interface
        (naming ``source``, the TOML without ``[bus]``).
    """
    try:
        found = dict(can.util.load_config())
    except (can.CanInterfaceNotImplementedError, ValueError, OSError) as exc:
        text = f"no [bus] table, and python-can's configuration: {exc}"
        raise ConfigError(text, file=source) from None
    missing = [k for k in ("interface", "channel") if not found.get(k)]
    if missing:
        raise ConfigError(
            "no [bus] table, and python-can's configuration (CAN_INTERFACE, CAN_CHANNEL, "
            f"~/.can, /etc/can.conf) names no {' or '.join(missing)}",
            file=source,
        )
    return with_overrides(
        BusConfig(interface=str(found["interface"]), channel=str(found["channel"])),
        bitrate=int(found["bitrate"]) if found.get("bitrate") else None,
        source=source,
    )


@dataclass(frozen=True)
class BusOverrides:
    """The command line's ``--interface``, ``--channel`` and ``--bitrate`` (``None``: not given),
    as python-can's own tools take them."""

    interface: str | None = None
    channel: str | None = None
    bitrate: int | None = None

    @property
    def given(self) -> bool:
        return any(v is not None for v in (self.interface, self.channel, self.bitrate))


def with_overrides(
    cfg: BusConfig,
    *,
    interface: str | None = None,
    channel: str | None = None,
    bitrate: int | None = None,
    source: str | None = None,
) -> BusConfig:
    """``cfg`` with the command line's ``--interface/--channel/--bitrate`` (those given).

    Raises
    ------
    ConfigError
        An unknown interface or a bitrate a CAN controller does not use.
    """
    if interface is not None:
        why = _known_interface(interface)
        if why is not None:
            raise ConfigError(why, file=source, key="--interface")
    if bitrate is not None and bitrate not in STANDARD_BITRATES:
        raise ConfigError(
            f"must be one of {', '.join(map(str, STANDARD_BITRATES))}, got {bitrate}",
            file=source,
            key="--bitrate",
        )
    return replace(
        cfg,
        interface=cfg.interface if interface is None else interface,
        channel=cfg.channel if channel is None else channel,
        bitrate=cfg.bitrate if bitrate is None else bitrate,
    )


# --- cycle time-outs ------------------------------------------------------------------------------

#: SYNC to the last TPDO of a cycle in lockstep (s): the simulator takes the time it takes on a
#: busy machine. Also the default of the master's ``Timeouts.tpdo_s``.
TPDO_TIMEOUT_LOCKSTEP_S = 2.0
#: SYNC to the last TPDO in realtime, in periods (a drive silent for several periods is lost) ...
TPDO_TIMEOUT_REALTIME_PERIODS = 5
#: ... and never below this (s).
TPDO_TIMEOUT_REALTIME_MIN_S = 0.01


def default_tpdo_timeout(clock: Clock, period_s: float) -> float:
    """The TPDO time-out of a run when the configuration sets none, s.

    Parameters
    ----------
    clock
        Lockstep: :data:`TPDO_TIMEOUT_LOCKSTEP_S`; realtime: :data:`TPDO_TIMEOUT_REALTIME_PERIODS`
        periods, at least :data:`TPDO_TIMEOUT_REALTIME_MIN_S`.
    period_s
        SYNC period, s.
    """
    if clock == Clock.LOCKSTEP:
        return TPDO_TIMEOUT_LOCKSTEP_S
    return max(TPDO_TIMEOUT_REALTIME_PERIODS * period_s, TPDO_TIMEOUT_REALTIME_MIN_S)


def open_bus(cfg: BusConfig) -> can.BusABC:
    """Open the python-can bus described by ``cfg``; the caller shuts it down.

    Raises
    ------
    BusError
        The interface or channel cannot be opened.
    """
    try:
        bus = can.Bus(
            interface=cfg.interface, channel=cfg.channel, bitrate=cfg.bitrate, **cfg.extra
        )
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as exc:
        raise BusError(f"cannot open CAN {cfg.interface} channel {cfg.channel!r}: {exc}") from None
    if cfg.interface == "socketcan" and cfg.receive_buffer > 0:
        size_receive_buffer(bus, cfg.receive_buffer)
    return bus


def size_receive_buffer(bus: can.BusABC, size: int) -> int:
    """Give a socketcan bus's socket a receive buffer of ``size`` bytes; returns what the kernel
    granted (it reports twice the value set, for its bookkeeping)."""
    sock = getattr(bus, "socket", None)
    if sock is None:
        return 0
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, size)
    except OSError:  # no CAP_NET_ADMIN: the unprivileged option, capped by rmem_max
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


def open_network(cfg: BusConfig) -> canopen.Network:
    """A connected :class:`canopen.Network` on the bus of ``cfg``; the caller disconnects it.

    The network owns the bus's only :class:`can.Notifier` (python-can allows one per bus): add
    further listeners with ``network.notifier.add_listener``.
    """
    bus = open_bus(cfg)
    network = canopen.Network(bus)
    # Instance attribute: the reader thread then notices a disconnect within this time.
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
    try:
        network.connect()
    except Exception as exc:
        bus.shutdown()
        raise BusError(f"cannot start the CAN reader on {cfg.channel!r}: {exc}") from None
    return network


# --- bus load -----------------------------------------------------------------------------------

#: Bits of a CAN 2.0A data frame outside the data field that bit stuffing can affect:
#: SOF 1, identifier 11, RTR 1, IDE 1, r0 1, DLC 4, CRC 15.
_STUFFED_OVERHEAD_STD = 34
#: The same for a 29-bit identifier (CAN 2.0B): SOF, 11 + SRR + IDE + 18, RTR, r1, r0, DLC, CRC.
_STUFFED_OVERHEAD_EXT = 54
#: Bits never stuffed: CRC delimiter 1, ACK slot + delimiter 2, EOF 7, intermission 3.
_FIXED_TAIL = 13


def frame_bits(data_bytes: int, *, extended: bool = False, worst_case: bool = True) -> int:
    """Bits one CAN data frame occupies on the bus, intermission included.

    Worst-case bit stuffing (one stuff bit per 4 bits after the first of the stuffed region,
    Davis et al. 2007): an 8-byte standard frame is 111 bits, 135 with stuffing.

    Parameters
    ----------
    data_bytes
        Data length, 0..8.
    extended
        29-bit identifier.
    worst_case
        Add the worst-case number of stuff bits.
    """
    if not 0 <= data_bytes <= 8:
        raise UsageError(f"a CAN 2.0 frame carries 0..8 data bytes, got {data_bytes}")
    stuffed = (_STUFFED_OVERHEAD_EXT if extended else _STUFFED_OVERHEAD_STD) + 8 * data_bytes
    stuff = (stuffed - 1) // 4 if worst_case else 0
    return stuffed + _FIXED_TAIL + stuff


@dataclass(frozen=True)
class BusLoad:
    """Bus occupancy of one SYNC cycle.

    Attributes
    ----------
    bits_per_cycle
        Bits of all frames of one cycle (worst-case stuffing).
    load
        Fraction of the bitrate used at the given period (1.0 = 100 %).
    max_rate_hz
        Highest cycle rate at 100 % load.
    """

    bits_per_cycle: int
    load: float
    max_rate_hz: float

    def rate_at(self, load: float) -> float:
        """Highest cycle rate (Hz) that keeps the bus at or below ``load`` (fraction)."""
        return self.max_rate_hz * load


def bus_load(
    n_nodes: int,
    period_s: float,
    bitrate: int,
    rpdo_bytes: Sequence[int] = (8,),
    tpdo_bytes: Sequence[int] = (8, 8),
    sync: bool = True,
    sync_bytes: int = 1,
) -> BusLoad:
    """Bus load of a cyclic exchange: per node its RPDOs and TPDOs, plus one SYNC per cycle.

    Parameters
    ----------
    n_nodes
        Number of drives.
    period_s
        SYNC period, s.
    bitrate
        Bitrate, bit/s.
    rpdo_bytes, tpdo_bytes
        Data length of each RPDO / TPDO of one node.
    sync
        Count the SYNC frame.
    sync_bytes
        SYNC data length (1 with a counter, 0 without).
    """
    if n_nodes < 0 or period_s <= 0.0 or bitrate <= 0:
        raise UsageError("n_nodes >= 0, period_s > 0 and bitrate > 0 are required")
    per_node = sum(frame_bits(b) for b in (*rpdo_bytes, *tpdo_bytes))
    bits = n_nodes * per_node + (frame_bits(sync_bytes) if sync else 0)
    max_rate = bitrate / bits if bits else math.inf
    return BusLoad(bits_per_cycle=bits, load=bits / (bitrate * period_s), max_rate_hz=max_rate)
