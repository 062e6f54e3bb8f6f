/* Sensor scalings of firmware/HARDWARE.md and configs/vehicle.yaml (imu:). The Python mirror
 * (sim_sitl/board_estimators.py) holds the same numbers; tests/unit/test_firmware_estimators.py checks
 * them against this library's exported copies. */
#ifndef QL_SENSORS_H
#define QL_SENSORS_H

#include <stdint.h>

#define QL_LOOP_HZ 500u
#define QL_DT_S 0.002f
#define QL_IMU_ZERO_COUNT INT32_C(512)
#define QL_IMU_COUNT_MAX 1023u
#define QL_GYRO_LSB_RAD_S 0.0102276f  /* 0.586 deg/s per count */
#define QL_ACCEL_LSB_M_S2 0.038246f   /* 0.0039 g per count */
#define QL_ACCEL_COUNTS_PER_G INT32_C(256)    /* 1 / 0.0039 g, rounded */
#define QL_GRAVITY_M_S2 9.80665f

#endif
