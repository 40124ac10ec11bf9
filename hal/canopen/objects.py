"""The object dictionary entries the backend and the simulated drives use (CiA 301, CiA 402, manufacturer).

Index and sub-index constants, named as the standards name them; every drive's EDS must define
every one listed in :data:`REQUIRED`. The objects of
the drives' own stop reactions (0x6007, 0x605A, 0x605E, 0x6087) are optional: a drive without them
is configured for what it has and reported (:mod:`hal.canopen.reaction`).
"""

from __future__ import annotations

# CiA 301 communication profile
DEVICE_TYPE = 0x1000  # u32: 0x0192 in the low word: a CiA 402 device
ERROR_REGISTER = 0x1001  # u8
COMMUNICATION_CYCLE_PERIOD = 0x1006  # u32, us: the SYNC period (optional)
CONSUMER_HEARTBEAT_TIME = 0x1016  # array of u32: node id << 16 | ms
PRODUCER_HEARTBEAT_TIME = 0x1017  # u16, ms
IDENTITY = 0x1018  # record: sub 1 vendor id, sub 2 product code, sub 3 revision, sub 4 serial (u32 each)
# CiA 402 device profile
ABORT_CONNECTION_OPTION_CODE = 0x6007  # i16: what the drive does when it loses the master (optional)
ERROR_CODE = 0x603F  # u16
CONTROLWORD = 0x6040  # u16
STATUSWORD = 0x6041  # u16
QUICK_STOP_OPTION_CODE = 0x605A  # i16: how a quick stop ends (optional)
DISABLE_OPERATION_OPTION_CODE = 0x605C  # i16: how "disable operation" ends (optional)
FAULT_REACTION_OPTION_CODE = 0x605E  # i16: how a fault the drive detects ends (optional)
MODES_OF_OPERATION = 0x6060  # i8
MODES_OF_OPERATION_DISPLAY = 0x6061  # i8
POSITION_ACTUAL = 0x6064  # i32, increments (the SEA's motor side)
VELOCITY_ACTUAL = 0x606C  # i32
TARGET_TORQUE = 0x6071  # i16, per mille of the rated torque
MAX_TORQUE = 0x6072  # u16, per mille of the rated torque (optional: written where the EDS has it)
MOTOR_RATED_TORQUE = 0x6076  # u32, mNm
TORQUE_ACTUAL = 0x6077  # i16, per mille of the rated torque (the spring's torque)
TORQUE_SLOPE = 0x6087  # u32, per mille of the rated torque per second (optional)
POSITION_ENCODER_RESOLUTION = 0x608F  # array: sub 1 increments, sub 2 motor revolutions
INTERPOLATION_TIME_PERIOD = 0x60C2  # record: sub 1 value (u8), sub 2 index (i8): value * 10^index s (optional)
ADDITIONAL_POSITION_ACTUAL = 0x60E4  # array of i32: further encoders (optional)
DIGITAL_INPUTS = 0x60FD  # u32: bits 16-31 manufacturer-specific inputs (optional)
SUPPORTED_DRIVE_MODES = 0x6502  # u32: bit n = mode n + 1 (optional in a drive's EDS)
# DAROR-01 SEA drive (manufacturer range)
LOAD_POSITION_ACTUAL = 0x2010  # i32, increments (the link)
LOAD_ENCODER_RESOLUTION = 0x2011  # u32, increments per revolution

#: Modes of operation: cyclic synchronous torque, profile torque.
MODE_CYCLIC_SYNCHRONOUS_TORQUE = 10
MODE_PROFILE_TORQUE = 4
#: The device type's low word for a CiA 402 drive.
CIA402_PROFILE = 0x0192

#: What the backend needs of every drive, whatever its make (CiA 301 and CiA 402): ``(index, sub, what)``.
#: The objects a drive reports its positions, torque and e-stops in come from its robot file
#: (:mod:`hal.canopen.profile`), and are checked against its EDS there.
REQUIRED: tuple[tuple[int, int, str], ...] = (
    (DEVICE_TYPE, 0, "device type"),
    (ERROR_REGISTER, 0, "error register"),
    (CONSUMER_HEARTBEAT_TIME, 1, "consumer heartbeat time"),
    (PRODUCER_HEARTBEAT_TIME, 0, "producer heartbeat time"),
    (0x1400, 1, "RPDO1 COB-ID"),
    (0x1400, 2, "RPDO1 transmission type"),
    (0x1600, 0, "RPDO1 mapping count"),
    (0x1800, 1, "TPDO1 COB-ID"),
    (0x1800, 2, "TPDO1 transmission type"),
    (0x1A00, 0, "TPDO1 mapping count"),
    (ERROR_CODE, 0, "error code"),
    (CONTROLWORD, 0, "controlword"),
    (STATUSWORD, 0, "statusword"),
    (MODES_OF_OPERATION, 0, "modes of operation"),
    (MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display"),
    (TARGET_TORQUE, 0, "target torque"),
)

#: 0x6007 abort connection option code (CiA 402): what a drive does when it loses the master.
ABORT_FAULT_SIGNAL = 1  # a fault (FAULT REACTION ACTIVE, then FAULT; the reaction is 0x605E's)
ABORT_DISABLE_VOLTAGE = 2  # disable voltage: SWITCH ON DISABLED at once, no torque (category 0)
ABORT_QUICK_STOP = 3  # quick stop: QUICK STOP ACTIVE, ended as 0x605A says
#: 0x605A quick stop option code and 0x605E fault reaction option code (CiA 402).
STOP_DISABLE_DRIVE = 0  # disable drive function: no torque at once
STOP_SLOW_DOWN_RAMP = 1  # slow down on the slow-down ramp (torque modes: the torque slope 0x6087), then disable
