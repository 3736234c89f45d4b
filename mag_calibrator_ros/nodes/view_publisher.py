# Copyright 2026 mag_calibrator_ros maintainers
# SPDX-License-Identifier: MIT
"""The calibration drawn for RViz: the buffer as PointCloud2 (raw and corrected, a per-point
``weight`` field: readings merged into it), the fitted surfaces and the direction cells as a
MarkerArray. Latched, published at a low rate and only while someone subscribes.

Everything it needs is imported with this module (the node's start-up): an import in the
diagnostics timer would hold the interpreter, and so the message path, while it runs.

PointCloud2 is built with numpy (sensor_msgs_py has no PyPI wheel). Magnetic fields are drawn at
``scale`` metres per tesla (default 1e4: a 50 µT field is a half-metre sphere).
"""

from __future__ import annotations

import math

from geometry_msgs.msg import Point
import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from mag_calibrator_ros.calibration.live.view import CalibrationView, Surface

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
TICK_TOLERANCE = 0.5
"""A view is due this share of the timer's period early: a tick a little early is not skipped
(with view_period equal to the tick, skipping one in two halved the rate)."""
_FIELDS = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
           for i, name in enumerate(('x', 'y', 'z', 'weight'))]


def point_cloud(header: Header, points: np.ndarray, weights: np.ndarray) -> PointCloud2:
    """An unorganised cloud of float32 x, y, z, weight."""
    data = np.column_stack([points, weights]).astype(np.float32)
    return PointCloud2(header=header, height=1, width=len(data), fields=_FIELDS,
                       is_bigendian=False, point_step=16, row_step=16 * len(data),
                       data=data.tobytes(), is_dense=True)


def _color(r: float, g: float, b: float, a: float) -> ColorRGBA:
    return ColorRGBA(r=r, g=g, b=b, a=a)


def _ellipsoid(header: Header, marker_id: int, namespace: str, surface: Surface, scale: float,
               color: ColorRGBA) -> Marker:
    marker = Marker(header=header, ns=namespace, id=marker_id, type=Marker.SPHERE,
                    action=Marker.ADD, color=color)
    centre = surface.centre * scale
    marker.pose.position.x, marker.pose.position.y, marker.pose.position.z = centre.tolist()
    x, y, z, w = quaternion(surface.rotation)
    marker.pose.orientation.x, marker.pose.orientation.y = float(x), float(y)
    marker.pose.orientation.z, marker.pose.orientation.w = float(z), float(w)
    diameters = 2.0 * surface.semi_axes * scale
    marker.scale.x, marker.scale.y, marker.scale.z = diameters.tolist()
    return marker


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a proper rotation matrix, by Shepperd's method
    (S. W. Shepperd, "Quaternion from rotation matrix", J. Guidance and Control 1(3), 1978):
    from its largest component, so it stays accurate at every angle."""
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = np.asarray(rotation, dtype=float)
    products = np.array([  # row i is 4 q_i (w, x, y, z)
        [1.0 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01],
        [m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20],
        [m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21],
        [m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22]])
    row = products[int(np.argmax(np.diag(products)))]
    w, x, y, z = (row / np.linalg.norm(row)).tolist()
    return x, y, z, w


def markers(header: Header, view: CalibrationView, scale: float) -> MarkerArray:
    """The raw-space ellipsoid, the corrected sphere, and the 80 direction cells on it (green
    where the buffer has samples)."""
    array = [Marker(header=header, action=Marker.DELETEALL)]
    if view.raw_surface is not None:
        array.append(_ellipsoid(header, 0, 'raw ellipsoid', view.raw_surface, scale,
                                _color(1.0, 0.6, 0.1, 0.25)))
    radius = view.field_strength
    if radius is None and len(view.raw):  # uncalibrated: cells drawn at the field's size
        radius = float(np.median(np.linalg.norm(view.raw - view.raw.mean(axis=0), axis=1)))
    if radius:
        sphere = Surface(np.zeros(3), np.eye(3), np.full(3, radius))
        if view.field_strength is not None:
            array.append(_ellipsoid(header, 1, 'corrected sphere', sphere, scale,
                                    _color(0.2, 0.6, 1.0, 0.2)))
        cells = Marker(header=header, ns='coverage cells', id=2, type=Marker.SPHERE_LIST,
                       action=Marker.ADD)
        cells.scale.x = cells.scale.y = cells.scale.z = 0.08 * radius * scale
        for direction, occupied in zip(view.cell_directions, view.occupied, strict=True):
            cells.points.append(_point(direction * radius * 1.05 * scale))
            cells.colors.append(_color(0.1, 0.8, 0.2, 0.9) if occupied
                                else _color(0.8, 0.1, 0.1, 0.6))
        array.append(cells)
    return MarkerArray(markers=array)


def _point(values: np.ndarray) -> Point:
    return Point(x=float(values[0]), y=float(values[1]), z=float(values[2]))


class ViewCadence:
    """When a view is due, on a timer ticking every ``tick_s``: a next-due time advanced by the
    period (the average rate is 1/period even when it is not a multiple of the tick), due up to
    TICK_TOLERANCE of a tick early, restarted from now after a pause (nobody watching)."""

    def __init__(self, tick_s: float) -> None:
        self._early = TICK_TOLERANCE * tick_s
        self._next = -math.inf

    def due(self, now: float, period: float) -> bool:
        """Whether a view is due at ``now`` (monotonic s) every ``period`` s (<= 0: never)."""
        if period <= 0.0 or now < self._next - self._early:
            return False
        late = now - self._next
        self._next = self._next + period if late < period else now + period
        return True


class ViewPublisher:
    """``~/view/raw``, ``~/view/corrected`` (PointCloud2) and ``~/view/markers`` (MarkerArray);
    ``published`` counts the views sent."""

    def __init__(self, node: Node, tick_s: float) -> None:
        self._node = node
        self._cadence = ViewCadence(tick_s)
        self.published = 0
        self._raw = node.create_publisher(PointCloud2, '~/view/raw', LATCHED)
        self._corrected = node.create_publisher(PointCloud2, '~/view/corrected', LATCHED)
        self._markers = node.create_publisher(MarkerArray, '~/view/markers', LATCHED)

    @property
    def watched(self) -> bool:
        return any(publisher.get_subscription_count() > 0
                   for publisher in (self._raw, self._corrected, self._markers))

    def due(self, now: float, period: float) -> bool:
        """Whether to publish a view now: someone watches and one is due every ``period``."""
        return self.watched and self._cadence.due(now, period)

    def publish(self, view: CalibrationView, frame_id: str, scale: float) -> None:
        header = Header(frame_id=frame_id, stamp=self._node.get_clock().now().to_msg())
        self._raw.publish(point_cloud(header, view.raw * scale, view.weights))
        if view.corrected is not None:
            self._corrected.publish(point_cloud(header, view.corrected * scale, view.weights))
        self._markers.publish(markers(header, view, scale))
        self.published += 1
