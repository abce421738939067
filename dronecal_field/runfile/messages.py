"""Records <-> Foxglove protobuf messages (the schemas of foxglove-schemas-protobuf).

The mapping is the contract's (shared/contracts/run-format.md) plus the
choices documented in docs/runfile.md: ``fix_type`` and the event ``type`` go in
the messages' key/value ``metadata``; ``/vehicle/attitude`` poses are body FLU
in ENU (frame_id ``enu``, ROS REP-103), and ``ned`` (body FRD in NED) is
accepted on reading.
"""

from __future__ import annotations

import math

import numpy as np

from dronecal_field.runfile.records import Attitude, Frame, GnssFix, RunEvent

IMAGE_TOPIC = "/camera/image"
VIDEO_TOPIC = "/camera/video"
FIX_TOPIC = "/gnss/fix"
ATTITUDE_TOPIC = "/vehicle/attitude"
EVENTS_TOPIC = "/events"
EVENTS_LOG_TOPIC = "/events/log"  # the same events as foxglove.Log: the Foxglove app shows no foxglove.Event, its Log panel shows these
MAVLINK_TOPIC_PREFIX = "/mavlink/"

IMAGE_SCHEMA = "foxglove.CompressedImage"
VIDEO_SCHEMA = "foxglove.CompressedVideo"
FIX_SCHEMA = "foxglove.LocationFix"
ATTITUDE_SCHEMA = "foxglove.PoseInFrame"
EVENT_SCHEMA = "foxglove.Event"

# ENU-from-NED axis swap and FRD-from-FLU body flip; both are their own inverse.
_T_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_F_FRD_FLU = np.diag([1.0, -1.0, -1.0])


def _timestamp(ns: int):
    from google.protobuf.timestamp_pb2 import Timestamp

    ns = int(ns)
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _ns(ts) -> int:
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _kv(d: dict[str, str]):
    from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair

    return [KeyValuePair(key=str(k), value=str(v)) for k, v in d.items()]


# --- images ---------------------------------------------------------------


def frame_to_proto(frame: Frame):
    """foxglove.CompressedImage of a frame (frame_id ``camera``)."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    return CompressedImage(
        timestamp=_timestamp(frame.timestamp_ns), frame_id="camera", data=frame.data, format=frame.format
    )


def frame_from_bytes(data: bytes, log_time_ns: int) -> Frame:
    """Frame of a serialized foxglove.CompressedImage; a message without a timestamp takes log_time."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    msg = CompressedImage.FromString(data)
    ts = _ns(msg.timestamp) if msg.HasField("timestamp") else int(log_time_ns)
    return Frame(timestamp_ns=ts, format=msg.format or "jpeg", data=msg.data)


def video_frame_to_proto(frame: Frame):
    """foxglove.CompressedVideo of one access unit (``format`` h264 / h265, Annex B; frame_id ``camera``)."""
    from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo

    return CompressedVideo(
        timestamp=_timestamp(frame.timestamp_ns), frame_id="camera", data=frame.data, format=frame.format
    )


def frame_from_video_bytes(data: bytes, log_time_ns: int) -> Frame:
    """Frame of a serialized foxglove.CompressedVideo (``format`` h264 / h265); no timestamp takes log_time."""
    from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo

    msg = CompressedVideo.FromString(data)
    ts = _ns(msg.timestamp) if msg.HasField("timestamp") else int(log_time_ns)
    return Frame(timestamp_ns=ts, format=(msg.format or "h264").lower(), data=msg.data)


# --- GNSS -----------------------------------------------------------------


def fix_to_proto(fix: GnssFix):
    """foxglove.LocationFix of a fix: ENU covariance row-major, type 2 (diagonal) or 3."""
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

    kwargs = {}
    if fix.covariance_enu is not None:
        cov = np.asarray(fix.covariance_enu, dtype=float).reshape(3, 3)
        diagonal = not np.any(cov - np.diag(np.diag(cov)))
        kwargs["position_covariance"] = [float(v) for v in cov.ravel()]
        kwargs["position_covariance_type"] = (
            LocationFix.DIAGONAL_KNOWN if diagonal else LocationFix.KNOWN
        )
    meta = {"fix_type": fix.fix_type} if fix.fix_type is not None else {}
    return LocationFix(
        timestamp=_timestamp(fix.timestamp_ns),
        frame_id="gnss",
        latitude=float(fix.lat_deg),
        longitude=float(fix.lon_deg),
        altitude=float(fix.alt_m),
        metadata=_kv(meta),
        **kwargs,
    )


def fix_from_bytes(data: bytes, log_time_ns: int) -> GnssFix:
    """GnssFix of a serialized foxglove.LocationFix.

    A covariance is kept when its type is not UNKNOWN and it has 9 finite
    entries; ``fix_type`` comes from the message metadata when present.
    """
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

    msg = LocationFix.FromString(data)
    cov = None
    if msg.position_covariance_type != LocationFix.UNKNOWN and len(msg.position_covariance) == 9:
        c = np.array(msg.position_covariance, dtype=float).reshape(3, 3)
        if np.all(np.isfinite(c)):
            cov = c
    fix_type = None
    for kv in msg.metadata:
        if kv.key == "fix_type":
            fix_type = kv.value or None
    ts = _ns(msg.timestamp) if msg.HasField("timestamp") else int(log_time_ns)
    return GnssFix(
        timestamp_ns=ts,
        lat_deg=float(msg.latitude),
        lon_deg=float(msg.longitude),
        alt_m=float(msg.altitude),
        covariance_enu=cov,
        fix_type=fix_type,
    )


# --- events ---------------------------------------------------------------


def event_to_proto(event: RunEvent):
    """foxglove.Event of a run event; its type is metadata key ``type`` (listed first)."""
    from foxglove_schemas_protobuf.Event_pb2 import Event

    meta = {"type": event.type}
    meta.update({k: v for k, v in event.metadata.items() if k != "type"})
    return Event(
        start_time=_timestamp(event.timestamp_ns),
        end_time=_timestamp(event.timestamp_ns + event.duration_ns),
        metadata=_kv(meta),
    )


WARNING_EVENTS = frozenset({"video_gap", "video_lag", "video_lost", "video_corrupt", "link_lost"})


def event_to_log(event: RunEvent):
    """foxglove.Log of a run event, for the Foxglove app's Log panel: ``hover 3.0 s: seq=4 hold_s=3.0 ...``."""
    from foxglove_schemas_protobuf.Log_pb2 import Log

    details = " ".join(f"{k}={v}" for k, v in event.metadata.items() if k != "type")
    return Log(
        timestamp=_timestamp(event.timestamp_ns),
        level=Log.WARNING if event.type in WARNING_EVENTS else Log.INFO,
        message=f"{event.type} {event.duration_ns / 1e9:.2f} s" + (f": {details}" if details else ""),
        name="dronecal-field",
    )


def event_from_bytes(data: bytes, log_time_ns: int) -> RunEvent:
    """RunEvent of a serialized foxglove.Event (type ``""`` when the metadata has none)."""
    from foxglove_schemas_protobuf.Event_pb2 import Event

    msg = Event.FromString(data)
    meta = {kv.key: kv.value for kv in msg.metadata}
    start = _ns(msg.start_time) if msg.HasField("start_time") else int(log_time_ns)
    end = _ns(msg.end_time) if msg.HasField("end_time") else start
    kind = meta.pop("type", "")
    return RunEvent(timestamp_ns=start, duration_ns=max(0, end - start), type=kind, metadata=meta)


# --- attitude -------------------------------------------------------------


def euler_to_matrix(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """(3, 3) R_ned_from_frd of Z-Y-X Euler angles (MAVLink ATTITUDE), radians."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def matrix_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """Z-Y-X Euler angles (roll, pitch, yaw), radians, of a (3, 3) R_ned_from_frd."""
    pitch = -math.asin(max(-1.0, min(1.0, float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return roll, pitch, yaw


def matrix_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a (3, 3) rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return x / n, y / n, z / n, w / n


def quaternion_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion (x, y, z, w); normalised first."""
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def attitude_to_proto(att: Attitude):
    """foxglove.PoseInFrame: orientation of body FLU in ENU (frame_id ``enu``), position 0."""
    from foxglove_schemas_protobuf.Pose_pb2 import Pose
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
    from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3

    R_ned_frd = euler_to_matrix(att.roll_rad, att.pitch_rad, att.yaw_rad)
    x, y, z, w = matrix_to_quaternion(_T_ENU_NED @ R_ned_frd @ _F_FRD_FLU)
    return PoseInFrame(
        timestamp=_timestamp(att.timestamp_ns),
        frame_id="enu",
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=x, y=y, z=z, w=w)),
    )


def attitude_from_bytes(data: bytes, log_time_ns: int) -> Attitude:
    """Attitude of a serialized foxglove.PoseInFrame (frame ``enu``: FLU in ENU; ``ned``: FRD in NED)."""
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    msg = PoseInFrame.FromString(data)
    q = msg.pose.orientation
    R = quaternion_to_matrix(q.x, q.y, q.z, q.w)
    if msg.frame_id.lower() != "ned":
        R = _T_ENU_NED @ R @ _F_FRD_FLU
    roll, pitch, yaw = matrix_to_euler(R)
    ts = _ns(msg.timestamp) if msg.HasField("timestamp") else int(log_time_ns)
    return Attitude(timestamp_ns=ts, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw)
