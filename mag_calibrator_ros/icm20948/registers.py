"""ICM-20948 and AK09916 register map (TDK DS-000189, AKM AK09916 datasheet; DESIGN.md §5).

One place for every address, bit and timing the driver and the simulator share, so the model of
the chip and the code that talks to it cannot drift apart.
"""

from __future__ import annotations

# --- ICM-20948 (accel/gyro; host of the AK09916) -------------------------------------------------
ICM20948_ADDRESSES = (0x68, 0x69)  # AD0 low / high (SparkFun and Adafruit boards: 0x69)
ICM20948_DEFAULT_ADDRESS = 0x69

REG_BANK_SEL = 0x7F  # in every bank; bank number in bits 5:4
BANK_SHIFT = 4
BANK_MASK = 0x30

# Bank 0
WHO_AM_I = 0x00
WHO_AM_I_VALUE = 0xEA
USER_CTRL = 0x03
USER_CTRL_I2C_MST_EN = 1 << 5
USER_CTRL_I2C_MST_RST = 1 << 1
PWR_MGMT_1 = 0x06
PWR_MGMT_1_DEVICE_RESET = 1 << 7
PWR_MGMT_1_SLEEP = 1 << 6
PWR_MGMT_1_CLKSEL_AUTO = 0x01
PWR_MGMT_1_RESET_VALUE = 0x41  # asleep, auto clock
INT_PIN_CFG = 0x0F
INT_PIN_CFG_BYPASS_EN = 1 << 1

DEVICE_RESET_WAIT_S = 0.010  # after PWR_MGMT_1 DEVICE_RESET
WAKE_WAIT_S = 0.001  # clock start-up after leaving sleep (the AK09916 itself needs none)

# --- AK09916 (magnetometer, on the host bus at 0x0C once bypass is on) ---------------------------
AK09916_ADDRESS = 0x0C
WIA1 = 0x00
WIA1_VALUE = 0x48  # AKM company ID
WIA2 = 0x01
WIA2_VALUE = 0x09  # AK09916 device ID
ST1 = 0x10
ST1_DRDY = 1 << 0
ST1_DOR = 1 << 1
HXL = 0x11  # HXL, HXH, HYL, HYH, HZL, HZH: int16 little-endian
TMPS = 0x17  # dummy register between the data and ST2
ST2 = 0x18
ST2_HOFL = 1 << 3
CNTL2 = 0x31
CNTL3 = 0x32
CNTL3_SRST = 1 << 0  # soft reset, self-clearing

BURST_START = ST1
BURST_LENGTH = ST2 - ST1 + 1  # 9 bytes ST1..ST2: reading ST2 last unlocks the data registers

MODE_POWER_DOWN = 0x00
MODE_SINGLE = 0x01
MODE_SELF_TEST = 0x10
CONTINUOUS_MODES = {10: 0x02, 20: 0x04, 50: 0x06, 100: 0x08}  # rate_hz -> CNTL2 value
CONTINUOUS_RATES = {mode: rate for rate, mode in CONTINUOUS_MODES.items()}

MODE_CHANGE_WAIT_S = 100e-6  # power-down -> other mode: >= 100 us
SOFT_RESET_WAIT_S = 0.001  # CNTL3 SRST completes well within 1 ms

MEASUREMENT_LIMIT = 32752  # |counts| beyond this is an overflow (ST2 HOFL)
TESLA_PER_LSB = 0.15e-6  # 0.15 uT per count

# AK09916 axes into the ICM-20948 accel/gyro frame: x kept, y and z inverted (REP-145).
AXIS_SIGNS = (1, -1, -1)
