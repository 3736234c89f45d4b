"""The RViz view: what is drawn (ROS-free) and the messages that carry it (over DDS)."""

from __future__ import annotations

from pathlib import Path
import sys

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from mag_calibrator_ros.calibration.fit.calibration import Calibration
from mag_calibrator_ros.calibration.fit.coverage import CELL_COUNT
from mag_calibrator_ros.calibration.live.view import calibration_surface, calibration_view
from mag_calibrator_ros.nodes.view_publisher import point_cloud

sys.path.insert(0, str(Path(__file__).resolve().parent))
from node_helpers import Ros, wait_for  # noqa: E402
from test_calibrator_node import HARD_IRON_UT, SOFT_IRON  # noqa: E402

CALIBRATION = Calibration(np.array([120e-6, -80e-6, 60e-6]),
                          np.array([[1.1, 0.1, 0.0], [0.1, 0.9, 0.05], [0.0, 0.05, 1.0]]), 50e-6)


def unit_vectors(n, seed=0):
    vectors = np.random.default_rng(seed).normal(size=(n, 3))
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def test_the_raw_surface_is_where_the_calibration_puts_the_field():
    surface = calibration_surface(CALIBRATION)
    assert np.isclose(np.linalg.det(surface.rotation), 1.0)
    points = surface.centre + (unit_vectors(200) * surface.semi_axes) @ surface.rotation.T
    magnitudes = np.linalg.norm(CALIBRATION.apply(points), axis=1)
    np.testing.assert_allclose(magnitudes, CALIBRATION.field_strength, rtol=1e-12)


def test_the_view_shows_points_corrected_and_the_cells_they_cover():
    truth = 50e-6 * unit_vectors(300)
    raw = np.linalg.solve(CALIBRATION.matrix, truth.T).T + CALIBRATION.offset
    view = calibration_view(raw, np.ones(300), CALIBRATION)
    np.testing.assert_allclose(view.corrected, truth, atol=1e-15)
    assert view.cell_directions.shape == (CELL_COUNT, 3) and view.occupied.sum() > 0.9 * CELL_COUNT
    half = raw[truth[:, 2] > 0]
    covered = calibration_view(half, np.ones(len(half)), CALIBRATION).occupied.sum()
    assert covered < 0.6 * CELL_COUNT
    uncalibrated = calibration_view(raw, np.ones(300), None)
    assert uncalibrated.corrected is None and uncalibrated.raw_surface is None
    assert uncalibrated.occupied.sum() > 0.9 * CELL_COUNT  # judged by the data's own shape


def decode(cloud: PointCloud2) -> np.ndarray:
    assert [field.name for field in cloud.fields] == ['x', 'y', 'z', 'weight']
    return np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(cloud.width, 4)


def test_point_cloud_carries_points_and_weights():
    points, weights = unit_vectors(7), np.arange(1.0, 8.0)
    cloud = point_cloud(Header(frame_id='imu_link'), points, weights)
    assert cloud.height == 1 and cloud.point_step * cloud.width == len(cloud.data)
    np.testing.assert_allclose(decode(cloud), np.column_stack([points, weights]), rtol=1e-6)


def test_the_node_draws_its_buffer_for_rviz_while_watched(tmp_path):
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ros = Ros()
    try:
        ros.driver('view', **{'sim.hard_iron_ut': HARD_IRON_UT, 'sim.soft_iron': SOFT_IRON,
                              'sim.motion': 'tumble', 'sim.seed': 2})
        node = ros.calibrator('view', view_period=0.5, progress_log_period=0.0,
                              calibration_file=str(tmp_path / 'c.yaml'))
        watcher = ros.add(Node('view_watcher', context=ros.context))
        received: dict[str, list] = {'raw': [], 'corrected': [], 'markers': []}
        for name, kind in (('raw', PointCloud2), ('corrected', PointCloud2),
                           ('markers', MarkerArray)):
            watcher.create_subscription(kind, f'/view/mag_calibrator/view/{name}',
                                        received[name].append, latched)
        assert wait_for(lambda: received['corrected'], timeout_s=60.0), (
            node.session.progress_text())
        raw = decode(received['raw'][-1])
        scale = node.get_parameter('view_scale').value
        assert len(raw) > 10 and np.all(raw[:, 3] >= 1.0)  # weights: readings per point
        centre = raw[:, :3].mean(axis=0) / scale
        assert np.linalg.norm(centre - np.array(HARD_IRON_UT) * 1e-6) < 40e-6
        markers = received['markers'][-1].markers
        assert markers[0].action == Marker.DELETEALL
        kinds = {marker.ns: marker for marker in markers[1:]}
        assert {'raw ellipsoid', 'corrected sphere', 'coverage cells'} <= set(kinds)
        assert len(kinds['coverage cells'].points) == CELL_COUNT
        assert received['raw'][-1].header.frame_id == 'imu_link'
    finally:
        ros.close()
