# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""ICM-20948 and AK09916 register map (TDK DS-000189, AKM AK09916 datasheet).

One place for every address, bit, scale and timing the driver and the simulator share, so the
model of the chip and the code that talks to it cannot drift apart.
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
USER_CTRL_FIFO_EN = 1 << 6  # the FIFO takes what FIFO_EN_1/2 select, at the sample rate
USER_CTRL_I2C_MST_EN = 1 << 5
USER_CTRL_I2C_MST_RST = 1 << 1
# LP_CONFIG (DS-000189 §8.3 p.37) resets to 0x40: I2C_MST_CYCLE = 1, the I2C master duty-cycled at
# its own rate (I2C_MST_ODR_CONFIG), whatever the gyro does; 0: it runs on the sensors' ODR.
LP_CONFIG = 0x05
LP_CONFIG_I2C_MST_CYCLE = 1 << 6
LP_CONFIG_ACCEL_CYCLE = 1 << 5
LP_CONFIG_GYRO_CYCLE = 1 << 4
LP_CONFIG_RESET_VALUE = LP_CONFIG_I2C_MST_CYCLE
PWR_MGMT_1 = 0x06
PWR_MGMT_1_DEVICE_RESET = 1 << 7
PWR_MGMT_1_SLEEP = 1 << 6
PWR_MGMT_1_LP_EN = 1 << 5
PWR_MGMT_1_CLKSEL_AUTO = 0x01
PWR_MGMT_1_RESET_VALUE = 0x41  # asleep, auto clock
PWR_MGMT_2 = 0x07
PWR_MGMT_2_DISABLE_ACCEL = 0x38  # bits 5:3, one per axis
PWR_MGMT_2_DISABLE_GYRO = 0x07  # bits 2:0
PWR_MGMT_2_ALL_ON = 0x00  # reset value: accel and gyro on
INT_PIN_CFG = 0x0F
INT_PIN_CFG_BYPASS_EN = 1 << 1
I2C_MST_STATUS = 0x17  # bank 0; read-to-clear (DS-000189 register 0x17)
I2C_MST_STATUS_SLV4_DONE = 1 << 6  # the SLV4 single transfer finished (with or without ACK)
I2C_MST_STATUS_SLV4_NACK = 1 << 4  # SLV4's slave did not acknowledge
I2C_MST_STATUS_SLV0_NACK = 1 << 0
INT_STATUS_1 = 0x1A
INT_STATUS_1_RAW_DATA_0_RDY = 1 << 0  # new accel/gyro/temp data; cleared by reading INT_STATUS_1
INT_STATUS_2 = 0x1B
INT_STATUS_2_FIFO_OVERFLOW = 0x1F  # FIFO_OVERFLOW_INT[4:0]; cleared by reading INT_STATUS_2
# ACCEL_X/Y/Z (0x2D), GYRO_X/Y/Z (0x33), TEMP (0x39): int16 big-endian, contiguous.
ACCEL_XOUT_H = 0x2D
TEMP_OUT_L = 0x3A
IMU_BURST_START = ACCEL_XOUT_H
IMU_BURST_LENGTH = TEMP_OUT_L - ACCEL_XOUT_H + 1  # 14 bytes: one coherent sample
# EXT_SLV_SENS_DATA_00..23 (bank 0, 0x3B..0x52) directly follow TEMP_OUT_L: the I2C master copies
# what its slaves 0-3 read there, in slave order, on every sample (DS-000189 registers 59-82). So
# one host burst from ACCEL_XOUT_H can carry the accel/gyro/temperature sample and the AK09916's.
EXT_SLV_SENS_DATA_00 = 0x3B
EXT_SLV_SENS_DATA_COUNT = 24

# The FIFO (bank 0; DS-000189 §7.1 and registers 0x66-0x72, pages not verified): FIFO_EN_1 bits
# 3:0 put slaves 0-3's EXT_SLV_SENS_DATA in, FIFO_EN_2 accel (bit 4), gyro z/y/x (bits 3-1) and
# temperature (bit 0); each sample appends the selected registers in register order, so with
# 0x1F a record is ACCEL_XOUT_H..TEMP_OUT_L, the 14 bytes of the data registers (ArduPilot's
# AP_InertialSensor_Invensensev2 reads 14-byte records). FIFO_RST bits 4:0 hold it empty while
# set; FIFO_MODE bit 0: 1 snapshot (no writes once full), 0 stream (the oldest bytes go).
# FIFO_COUNTH/L: bytes in it, read high then low (reading FIFO_COUNTH latches both); FIFO_R_W:
# each byte read pops one. 512 bytes (PX4's ICM20948 driver, FIFO::SIZE).
FIFO_EN_1 = 0x66
FIFO_EN_2 = 0x67
FIFO_EN_2_ACCEL = 1 << 4
FIFO_EN_2_GYRO = 0x0E  # GYRO_Z, GYRO_Y, GYRO_X
FIFO_EN_2_TEMP = 1 << 0
FIFO_EN_2_ALL = FIFO_EN_2_ACCEL | FIFO_EN_2_GYRO | FIFO_EN_2_TEMP
FIFO_RST = 0x68
FIFO_RST_ALL = 0x1F
FIFO_MODE = 0x69
FIFO_MODE_SNAPSHOT = 0x1F  # every FIFO's bit (ArduPilot writes 0x0F, PX4 bit 0)
FIFO_COUNTH = 0x70
FIFO_COUNTL = 0x71
FIFO_R_W = 0x72
FIFO_COUNT_HIGH_MASK = 0x1F  # FIFO_CNT[12:8]
FIFO_SIZE = 512
FIFO_RECORD_LENGTH = IMU_BURST_LENGTH  # accel, gyro, temperature
FIFO_EMPTY_BYTE = 0xFF  # what a read of an empty FIFO returns (the family's DS-000178 p.68)

# Bank 2 (configuration; reached through REG_BANK_SEL, then back to bank 0 for data)
CONFIG_BANK = 2
GYRO_SMPLRT_DIV = 0x00  # 8-bit divider
GYRO_CONFIG_1 = 0x01  # bits 5:3 GYRO_DLPFCFG, 2:1 GYRO_FS_SEL, 0 GYRO_FCHOICE (1 = DLPF on)
# ODR_ALIGN_EN (DS-000189 §10.10, page not verified): 1 aligns the sample clocks' start times
# whenever GYRO_SMPLRT_DIV, ACCEL_SMPLRT_DIV_1/2 or I2C_MST_ODR_CONFIG is written; 0: each keeps
# running.
ODR_ALIGN_EN = 0x09
ACCEL_SMPLRT_DIV_1 = 0x10  # divider bits 11:8
ACCEL_SMPLRT_DIV_2 = 0x11  # divider bits 7:0
ACCEL_CONFIG = 0x14  # bits 5:3 ACCEL_DLPFCFG, 2:1 ACCEL_FS_SEL, 0 ACCEL_FCHOICE (1 = DLPF on)
CONFIG_DLPF_SHIFT = 3
CONFIG_FS_SHIFT = 1
CONFIG_FCHOICE = 1 << 0
GYRO_CONFIG_1_RESET_VALUE = 0x01
ACCEL_CONFIG_RESET_VALUE = 0x01

# Bank 3: the ICM-20948's own I2C master on the auxiliary bus, where the AK09916 sits
# (DS-000189 §11; §11.9-11.10 are on p.71, the pages of the others not verified). A round of the
# master runs slaves 0-3, then a pending SLV4 transfer. With LP_CONFIG I2C_MST_CYCLE = 1 (reset,
# §8.3 p.37) rounds come at 1.1 kHz / 2^I2C_MST_ODR_CONFIG[3:0] on the master's own duty-cycle
# clock (§11.1); with I2C_MST_CYCLE = 0 on the gyro's ODR (the accel's with the gyro off;
# I2C_MST_ODR_CONFIG's with both off, §11.1).
MASTER_BANK = 3
I2C_MST_ODR_CONFIG = 0x00
I2C_MST_ODR_CONFIG_MASK = 0x0F
MASTER_CYCLE_RATE_HZ = 1100.0  # I2C_MST_ODR_CONFIG = 0
I2C_MST_CTRL = 0x01  # bit 7 MULT_MST_EN, bit 4 I2C_MST_P_NSR, bits 3:0 I2C_MST_CLK
I2C_MST_CTRL_P_NSR = 1 << 4  # stop (not repeated start) between slave reads
I2C_MST_CLK_345_KHZ = 0x07  # recommended setting (345.6 kHz, 46.67 % duty; page not verified)
I2C_MST_DELAY_CTRL = 0x02  # bit 7 DELAY_ES_SHADOW, bit 4 I2C_SLV4_DELAY_EN, bits 3:0 SLVn
I2C_MST_DELAY_ES_SHADOW = 1 << 7  # shadow EXT_SLV_SENS_DATA only once every slave's data is in
# I2C_SLVn_DELAY_EN (bits 4:0, n = 0..4; §11.3): a delayed slave is accessed only on one round in
# (1 + I2C_SLV4_DLY), I2C_SLV4_DLY being I2C_SLV4_CTRL bits 4:0 (§11.22: bank-3 sections run in
# address order, §11.9 = 0x08 on p.71, so 0x15 is §11.22, §11.21 being I2C_SLV4_REG; pages of
# §11.3 and §11.22 not verified).
I2C_SLV4_DELAY_EN = 1 << 4
I2C_SLV4_DLY_MASK = 0x1F
I2C_SLV0_ADDR = 0x03  # bit 7 I2C_SLV0_RNW (1 = read), bits 6:0 the slave's 7-bit address
I2C_SLV0_REG = 0x04  # first register of the slave to read
I2C_SLV0_CTRL = 0x05  # bit 7 EN, bit 6 BYTE_SW, bit 5 REG_DIS, bit 4 GRP, bits 3:0 LENG
I2C_SLV0_DO = 0x06
I2C_SLV_STRIDE = 4  # SLV1..SLV3 repeat ADDR/REG/CTRL/DO at +4, +8, +12
I2C_SLV4_ADDR = 0x13
I2C_SLV4_REG = 0x14
I2C_SLV4_CTRL = 0x15  # bit 7 EN (one transfer), bit 6 INT_EN, bit 5 REG_DIS, bits 4:0 DLY
I2C_SLV4_DO = 0x16  # byte SLV4 writes
I2C_SLV4_DI = 0x17  # byte SLV4 read
I2C_SLV_RNW = 1 << 7
I2C_SLV_EN = 1 << 7
I2C_SLV_LENG_MASK = 0x0F

# Output data rate with FCHOICE = 1: 1125 / (1 + divider) Hz, each sensor by its own divider
# (GYRO_SMPLRT_DIV 8 bits, ACCEL_SMPLRT_DIV_1/2 12 bits; DS-000189 tables 16 and 18, §10.1 and
# §10.11-10.12, pages not verified: 1.125 kHz, the gyroscope's rounded to 1.1 kHz in places).
# With FCHOICE = 0 the DLPF and the divider are bypassed: the gyroscope runs at 9 kHz, the
# accelerometer at 4.5 kHz (tables 16 and 18, pages not verified).
# The driver offers DLPFCFG 1-6 (the filters the datasheet's tables give a bandwidth for that
# rounds well below the rate); the simulator models all eight.
INTERNAL_RATE_HZ = 1125.0
GYRO_BYPASS_RATE_HZ = 9000.0
ACCEL_BYPASS_RATE_HZ = 4500.0
GYRO_DIVIDER_MAX = 0xFF
ACCEL_DIVIDER_MAX = 0xFFF
DLPF_SETTINGS = (1, 2, 3, 4, 5, 6)
# DLPFCFG -> (3 dB bandwidth, noise bandwidth) in Hz, DS-000189 tables 16 (gyro) and 18 (accel)
# (pages not verified).
GYRO_DLPF_HZ = {0: (196.6, 229.8), 1: (151.8, 187.6), 2: (119.5, 154.3), 3: (51.2, 73.3),
                4: (23.9, 35.9), 5: (11.6, 17.8), 6: (5.7, 8.9), 7: (361.4, 376.5)}
ACCEL_DLPF_HZ = {0: (246.0, 265.0), 1: (246.0, 265.0), 2: (111.4, 136.0), 3: (50.4, 68.8),
                 4: (23.9, 34.4), 5: (11.5, 17.0), 6: (5.7, 8.3), 7: (473.0, 499.0)}
GYRO_BYPASS_HZ = (12106.0, 12316.0)  # FCHOICE = 0
ACCEL_BYPASS_HZ = (1209.0, 1248.0)

# Full-scale ranges: FS_SEL code and sensitivity (LSB per g, LSB per deg/s).
ACCEL_RANGES_G = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}
GYRO_RANGES_DPS = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}
STANDARD_GRAVITY = 9.80665  # m/s^2 per g: the accelerometer's sensitivity is per standard g
INT16_MIN, INT16_MAX = -32768, 32767  # a saturated axis reads the rail

# Temperature: degC = (TEMP_OUT - RoomTemp_Offset) / 333.87 + 21, RoomTemp_Offset = 0.
TEMP_SENSITIVITY_LSB_PER_C = 333.87
TEMP_OFFSET_C = 21.0

DEVICE_RESET_WAIT_S = 0.010  # after PWR_MGMT_1 DEVICE_RESET
WAKE_WAIT_S = 0.001  # clock start-up after leaving sleep (the AK09916 itself needs none)
SENSOR_STARTUP_S = 0.035  # gyro start-up from sleep (DS-000189 table 1, page not verified)
ACCEL_STARTUP_S = 0.020  # accel start-up from sleep (DS-000189 table 2, page not verified)

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
HZH = 0x16
TMPS = 0x17  # dummy register between the data and ST2
ST2 = 0x18
ST2_HOFL = 1 << 3
CNTL2 = 0x31
CNTL3 = 0x32
CNTL3_SRST = 1 << 0  # soft reset, self-clearing

# Through the I2C master, every round slave 0 reads ST1..HZH (7 bytes) and slave 1 ST2 (1 byte;
# reading it ends the AK09916's data read and releases the next sample), so the copy is ST1,
# HXL..HZH, ST2 in EXT_SLV_SENS_DATA_00..07, without the dummy TMPS: 8 bytes per look. The copied
# ST1 says whether that round found a new sample (DRDY).
MAG_MASTER_SLV0_LENGTH = HZH - ST1 + 1
MAG_MASTER_LENGTH = MAG_MASTER_SLV0_LENGTH + 1
# A round of the master ends in a few hundred microseconds; a single SLV4 transfer is done by the
# next round, i.e. within one round period: the driver polls I2C_MST_STATUS for this many.
SLV4_TIMEOUT_PERIODS = 4

# A data read starts at HXL (clears DRDY/DOR, protects the data) and must end with ST2 (releases
# it): polling ST1 alone is cheap and the 8-byte burst runs only when DRDY is set.
MAG_BURST_START = HXL
MAG_BURST_LENGTH = ST2 - HXL + 1  # 8 bytes HXL..ST2

MODE_POWER_DOWN = 0x00
MODE_SINGLE = 0x01
MODE_SELF_TEST = 0x10
CONTINUOUS_MODES = {10: 0x02, 20: 0x04, 50: 0x06, 100: 0x08}  # rate_hz -> CNTL2 value
CONTINUOUS_RATES = {mode: rate for rate, mode in CONTINUOUS_MODES.items()}

MODE_CHANGE_WAIT_S = 100e-6  # power-down -> other mode: >= 100 us
# Single measurement (CNTL2 0x01) and self-test (0x10) take one sample, set DRDY and return to
# power-down by themselves. DRDY: DS-000189 §13.2 p.78; CNTL2 codes: §13.5 from p.79 (the codes
# after continuous mode 1 on a page not verified); the return to power-down: AK09916 datasheet
# (section and page not verified).
SINGLE_MEASUREMENT_S = 0.0072  # measurement time, also before a continuous mode's first sample
# Self-test judgement (AK09916 datasheet, section and page not verified): an internal field of
# -200..200 (x, y) and -1000..-200 (z) counts.
SELF_TEST_LIMITS = ((-200, 200), (-200, 200), (-1000, -200))
SOFT_RESET_WAIT_S = 0.001  # CNTL3 SRST completes well within 1 ms

MEASUREMENT_LIMIT = 32752  # |counts| beyond this is an overflow (ST2 HOFL; DS-000189 p.79)
TESLA_PER_LSB = 0.15e-6  # 0.15 uT per count

# AK09916 axes into the ICM-20948 accel/gyro frame: x kept, y and z inverted (REP-145).
AXIS_SIGNS = (1, -1, -1)

# --- the I2C bus ---------------------------------------------------------------------------------
I2C_STANDARD_FAST_HZ = 400_000  # fast-mode clock the bus share is quoted against
