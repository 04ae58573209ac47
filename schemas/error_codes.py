"""Meaning of 0x603F error codes (and EMCY error codes): the CiA 301 / CiA 402 (IEC 61800-7-201)
error code table as data.

An error code is 16 bits: the high byte's upper nibble is the class (0x2xxx current, 0x3xxx
voltage, ...), the high byte the sub-class (0x23xx current on the device output side), the
whole code a specific error (0x2310 continuous over-current). :func:`describe` returns the text
of the most specific entry that is known: the code itself, else its sub-class, else its class;
0xFF00..0xFFFF are manufacturer-specific. Pure data and a lookup: cheap enough for every status.
"""

from __future__ import annotations

#: Specific codes and sub-classes (CiA 301 table 21, CiA 402 / IEC 61800-7-201 annex, ETG.1000.6
#: for the EtherCAT 0xA0xx codes). Sub-class entries end in 00.
ERROR_CODES: dict[int, str] = {
    0x0000: "no error",
    0x1000: "generic error",
    # 0x2xxx current
    0x2100: "current, device input side",
    0x2110: "short circuit/earth leakage (input)",
    0x2120: "earth leakage (input)",
    0x2130: "short circuit (input)",
    0x2200: "current inside the device",
    0x2211: "internal current no. 1",
    0x2212: "internal current no. 2",
    0x2214: "over-current in ramp function",
    0x2215: "over-current in the sequence",
    0x2220: "continuous current (device internal)",
    0x2230: "short circuit/earth leakage (device internal)",
    0x2240: "earth leakage (device internal)",
    0x2250: "short circuit (device internal)",
    0x2300: "current, device output side",
    0x2310: "continuous over-current",
    0x2311: "continuous over-current no. 1",
    0x2312: "continuous over-current no. 2",
    0x2320: "short circuit/earth leakage (motor side)",
    0x2330: "earth leakage (motor side)",
    0x2340: "short circuit (motor side)",
    0x2350: "load level fault (I2t, thermal state)",
    # 0x3xxx voltage
    0x3100: "mains voltage",
    0x3110: "mains over-voltage",
    0x3120: "mains under-voltage",
    0x3130: "phase failure",
    0x3140: "mains frequency",
    0x3200: "DC link voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3230: "load error",
    0x3300: "output voltage",
    0x3310: "output over-voltage",
    # 0x4xxx temperature
    0x4100: "ambient temperature",
    0x4110: "excess ambient temperature",
    0x4120: "too low ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess device temperature",
    0x4220: "too low device temperature",
    0x4300: "drive temperature",
    0x4310: "excess drive temperature",
    0x4320: "too low drive temperature",
    0x4400: "supply temperature",
    0x4410: "excess supply temperature",
    0x4420: "too low supply temperature",
    # 0x5xxx device hardware
    0x5100: "supply (low voltage)",
    0x5200: "control",
    0x5210: "measurement circuit",
    0x5220: "computing circuit",
    0x5300: "operating unit",
    0x5400: "power section",
    0x5410: "output stages",
    0x5420: "chopper",
    0x5430: "input stages",
    0x5440: "contacts",
    0x5441: "contact 1 (enable input)",
    0x5450: "fuses",
    0x5500: "data storage",
    0x5530: "flash/EEPROM",
    # 0x6xxx device software
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data record",
    0x6310: "loss of parameters",
    0x6320: "parameter error",
    # 0x7xxx additional modules
    0x7100: "power",
    0x7110: "brake chopper",
    0x7111: "brake chopper failure",
    0x7112: "brake chopper over-current",
    0x7120: "motor",
    0x7121: "motor blocked",
    0x7122: "motor error or commutation malfunction",
    0x7123: "motor tilted",
    0x7200: "measurement circuit",
    0x7300: "sensor",
    0x7301: "tacho fault",
    0x7302: "tacho wrong polarity",
    0x7303: "resolver 1 fault",
    0x7304: "resolver 2 fault",
    0x7305: "incremental sensor 1 fault",
    0x7306: "incremental sensor 2 fault",
    0x7310: "speed",
    0x7320: "position",
    0x7400: "computation circuit",
    0x7500: "communication",
    0x7510: "serial interface no. 1",
    0x7520: "serial interface no. 2",
    0x7600: "data storage (external)",
    # 0x8xxx monitoring
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8300: "torque control",
    0x8311: "excess torque",
    0x8312: "difficult start-up",
    0x8313: "standstill torque",
    0x8321: "insufficient torque",
    0x8331: "torque fault",
    0x8400: "velocity speed controller",
    0x8500: "position controller",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
    0x8700: "sync controller",
    0x8800: "winding controller",
    0x8900: "process data monitoring",
    0x8A00: "control",
    # 0x9xxx external
    0x9000: "external error",
    # EtherCAT (ETG.1000.6, CoE emergency)
    0xA000: "EtherCAT state change PRE-OP -> SAFE-OP failed",
    0xA001: "EtherCAT state change SAFE-OP -> OP failed",
    # 0xFxxx additional functions
    0xF000: "additional functions",
    0xF001: "deceleration",
    0xF002: "sub-synchronous run",
    0xF003: "stroke operation",
    0xF004: "control",
}

#: Error code classes (the upper nibble), the fallback for codes the table does not list.
ERROR_CLASSES: dict[int, str] = {
    0x0: "error reset or no error",
    0x1: "generic error",
    0x2: "current",
    0x3: "voltage",
    0x4: "temperature",
    0x5: "device hardware",
    0x6: "device software",
    0x7: "additional modules",
    0x8: "monitoring",
    0x9: "external error",
    0xA: "EtherCAT state machine",
    0xB: "reserved",
    0xC: "reserved",
    0xD: "reserved",
    0xE: "reserved",
    0xF: "additional functions",
}

MANUFACTURER_SPECIFIC = range(0xFF00, 0x10000)


def describe(code: int) -> str:
    """The meaning of error code ``code`` (0x603F), most specific first; '' for 0 (no error).

    >>> describe(0x2310), describe(0x2399), describe(0x4999), describe(0xFF42)
    ('continuous over-current', 'current, device output side (0x2399)', 'temperature (0x4999)', 'manufacturer-specific error (0xFF42)')
    """
    if not code:
        return ""
    code &= 0xFFFF
    if code in ERROR_CODES:
        return ERROR_CODES[code]
    if code in MANUFACTURER_SPECIFIC:
        return f"manufacturer-specific error (0x{code:04X})"
    sub = ERROR_CODES.get(code & 0xFF00)
    if sub is not None:
        return f"{sub} (0x{code:04X})"
    return f"{ERROR_CLASSES[code >> 12]} (0x{code:04X})"
