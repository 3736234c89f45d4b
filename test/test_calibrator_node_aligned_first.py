"""mag_calibrator over real rclpy/DDS with an IMU (issue #24): the first automatic calibration
waits for the still tilts that align it, says so on /diagnostics, and imu/mag_corrected is in the
IMU frame from its first message. The stream: a magnetometer mounted 3 deg off the accelerometer,
tumbled (coverage, never still) then held still at one tilt after another."""

from __future__ import annotations

import time

from node_helpers import Probe, angle_deg, vector, wait_for
import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Imu
from test_alignment_wait import tumble_then_poses

RATE_HZ = 100.0
PACE = 1.0  # stream seconds a wall second: decisions follow the stamps


def test_the_first_corrected_message_is_aligned_to_the_imu(ros):
    namespace = 'aligned_first'
    mag, accel, gyro, misalignment = tumble_then_poses(12.0, 45.0)
    truth = mag - (120e-6, -80e-6, 60e-6)  # the sensor's hard iron off: the field it read
    truth = truth @ misalignment.T  # ... turned into the IMU frame
    calibrator = ros.calibrator(namespace, progress_log_period=0.0, view_period=0.0)
    probe = Probe(ros, namespace)
    feeder = ros.add(Node('imu_feeder', namespace=namespace, context=ros.context))
    imu = feeder.create_publisher(Imu, 'imu/data_raw', QoSProfile(depth=100))
    try:
        assert wait_for(lambda: probe.connected_to(calibrator)
                        and imu.get_subscription_count() >= 1)
        stamps = {}
        started = time.monotonic()
        for index in range(len(mag)):
            sec, nanosec = divmod(round(index * 1e9 / RATE_HZ), 1_000_000_000)
            msg = Imu()
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
            msg.header.frame_id = 'imu_link'
            a = msg.linear_acceleration
            a.x, a.y, a.z = (float(v) for v in accel[index])
            w = msg.angular_velocity
            w.x, w.y, w.z = (float(v) for v in gyro[index])
            imu.publish(msg)
            probe.send(mag[index], sec, nanosec)
            stamps[(sec, nanosec)] = index
            ahead = index / RATE_HZ / PACE - (time.monotonic() - started)
            if ahead > 0:
                time.sleep(ahead)
        assert wait_for(lambda: len(probe.corrected) >= 50, timeout_s=60.0), (
            calibrator.session.progress_text())
        corrected = probe.take_corrected()
        first = stamps[(corrected[0].header.stamp.sec, corrected[0].header.stamp.nanosec)]
        assert first / RATE_HZ > 12.0  # ready while tumbling, held back until aligned
        errors = [angle_deg(vector(msg), truth[stamps[(msg.header.stamp.sec,
                                                       msg.header.stamp.nanosec)]])
                  for msg in corrected[:50]]
        assert np.sqrt(np.mean(np.square(errors))) < 1.0  # unaligned: 3 deg
        messages = [status.message for status in probe.statuses('mag_calibrator: calibration')]
        assert any('waiting for still tilts' in message for message in messages)
        assert calibrator.session.adoptions.get('auto') == 1
    finally:
        for node in (feeder, probe, calibrator):
            ros.remove(node)
