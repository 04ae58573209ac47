"""The simulated drive types (:class:`DriveProfile`), their emergencies and the controlword's
device command coding: the data the drive model (:mod:`bus_agent.sim.drive_model`) runs on."""

from __future__ import annotations

from dataclasses import dataclass

from bus_agent.cia402.states import Controlword, Mode

# --------------------------------------------------------------------------------------------
# Emergency and profiles


@dataclass(frozen=True)
class Emcy:
    """CoE emergency (service 1): error code u16, error register u8 (0x1001), 5 manufacturer bytes."""

    error_code: int
    error_register: int
    data: bytes = b"\0" * 5


def _modes_bitmap(*modes: Mode) -> int:
    bits = 0
    for m in modes:
        bits |= 1 << m.supported_bit
    return bits


_COMMON_MODES = _modes_bitmap(Mode.PROFILE_POSITION, Mode.PROFILE_VELOCITY, Mode.PROFILE_TORQUE, Mode.HOMING,
                              Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY, Mode.CYCLIC_SYNC_TORQUE)


@dataclass(frozen=True)
class DriveProfile:
    """What makes one simulated drive type differ from another."""

    name: str               # "generic" | "indy7"
    vendor_id: int
    product_code: int
    revision: int
    device_name: str
    supported_modes: int    # 0x6502 bitmap
    statusword_extra: int   # bits OR-ed into the statusword (indy7: 0x0200 remote bit)
    not_ready_on_power_up: bool  # indy7: sits in not_ready_to_switch_on (0x0220), accepts Shutdown there
    self_test_steps: int = 2     # generic: steps in not_ready_to_switch_on before transition 1
    mode_echo_delay_steps: int = 0  # extra steps before 0x6061 echoes 0x6060
    torque_accel: float = 10_000.0  # increments/s^2 per per-mille of torque (PT/CST kinematics)
    power_on_position: int = 0   # absolute encoder: position at power-on = this * serial
    power_on_mode: int = 0       # 0x6060/0x6061 at power-on (a drive's stored default mode)
    home_switch_position: int | None = 5_000  # 0x60FD bit 2 active at and above (None: no switch)


PROFILES: dict[str, DriveProfile] = {
    "generic": DriveProfile(
        name="generic", vendor_id=0x00000ABC, product_code=0x00402001, revision=0x00010000,
        device_name="SimDrive402", supported_modes=_COMMON_MODES, statusword_extra=0x0200,
        not_ready_on_power_up=False,
    ),
    # Neuromeka Indy7 joint as seed 004 reports it: 0x0220 -> 0x0221 -> 0x0233 -> 0x0237.
    # Identity values are the simulator's own, not the real drive's.
    "indy7": DriveProfile(
        name="indy7", vendor_id=0x00000ABC, product_code=0x00402007, revision=0x00010000,
        device_name="SimIndy7Joint", supported_modes=_COMMON_MODES, statusword_extra=0x0200,
        not_ready_on_power_up=True,
    ),
}


# --------------------------------------------------------------------------------------------
# Controlword decoding (CiA 402 Table "command coding", bits 7,3,2,1,0)


#: The device command coding of the controlword (CiA 402, "command coding": bits 3, 2, 1, 0; bit
#: 7, fault reset, is an edge handled by the model), as (mask, command): the command whose bits
#: under the mask match, in the order the standard resolves overlaps: disable voltage (bit 1 = 0)
#: wins over quick stop (bit 2 = 0).
COMMAND_CODING: tuple[tuple[int, Controlword], ...] = (
    (0x02, Controlword.DISABLE_VOLTAGE),   # x x 0 x
    (0x06, Controlword.QUICK_STOP),        # x 0 1 x
    (0x07, Controlword.SHUTDOWN),          # x 1 1 0
    (0x0F, Controlword.SWITCH_ON),         # 0 1 1 1 (also disable operation)
    (0x0F, Controlword.ENABLE_OPERATION),  # 1 1 1 1
)
#: :data:`COMMAND_CODING` resolved for each of the 16 values of bits 3..0 (one lookup per step).
_COMMAND_OF_BITS: tuple[Controlword, ...] = tuple(next(c for mask, c in COMMAND_CODING if bits & mask == c & mask)
                                                  for bits in range(16))


def decode_command(controlword: int) -> Controlword:
    """The device command of a controlword's bits 3, 2, 1, 0 (:data:`COMMAND_CODING`)."""
    return _COMMAND_OF_BITS[controlword & 0x0F]
