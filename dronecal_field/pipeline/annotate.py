"""An annotated COPY of a run: the original records plus the calibration, for Foxglove.

Adds ``/camera/calibration`` (foxglove.CameraCalibration, one message at the
first detection, so Foxglove's image panel can undistort and project) and
``/camera/annotations`` (foxglove.ImageAnnotations, one per detection: the
centre, the ArUco outline, the window number). The original file is never
modified: MCAP has no append, and a run is evidence.

The copy streams record by record with mcap's StreamReader, which also reads
a run that was cut off (it stops at the damaged end); memory holds one chunk.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

CALIBRATION_TOPIC = "/camera/calibration"
ANNOTATIONS_TOPIC = "/camera/annotations"


def _file_descriptor_set(message_class) -> bytes:
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


def _stamp(field, t_ns: int) -> None:
    field.seconds = int(t_ns) // 1_000_000_000
    field.nanos = int(t_ns) % 1_000_000_000


def calibration_message(camera, t_ns: int, frame_id: str = "camera"):
    """foxglove.CameraCalibration of a camera (plumb_bob; R identity; P = [K | 0])."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration

    msg = CameraCalibration()
    _stamp(msg.timestamp, t_ns)
    msg.frame_id = frame_id
    msg.width, msg.height = int(camera.width), int(camera.height)
    msg.distortion_model = "plumb_bob"
    msg.D.extend(float(v) for v in camera.distortion.as_array())
    K = camera.intrinsics.matrix
    msg.K.extend(float(v) for v in K.ravel())
    msg.R.extend(float(v) for v in np.eye(3).ravel())
    msg.P.extend(float(v) for v in np.c_[K, np.zeros(3)].ravel())
    return msg


def annotation_message(detection, label: str, used: bool):
    """foxglove.ImageAnnotations of one detection: a circle at the centre, the outline, a label."""
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation

    msg = ImageAnnotations()
    colour = (0.1, 0.8, 0.2, 1.0) if used else (0.9, 0.5, 0.1, 1.0)
    circle = msg.circles.add()
    _stamp(circle.timestamp, detection.timestamp_ns)
    circle.position.x, circle.position.y = detection.u_px, detection.v_px
    circle.diameter = max(4.0, 0.5 * detection.size_px)
    circle.thickness = 1.5
    circle.outline_color.r, circle.outline_color.g, circle.outline_color.b, circle.outline_color.a = colour
    if detection.corners_px is not None:
        outline = msg.points.add()
        _stamp(outline.timestamp, detection.timestamp_ns)
        outline.type = PointsAnnotation.LINE_LOOP
        for u, v in np.asarray(detection.corners_px):
            p = outline.points.add()
            p.x, p.y = float(u), float(v)
        outline.thickness = 1.0
        outline.outline_color.r, outline.outline_color.g, outline.outline_color.b, outline.outline_color.a = colour
    text = msg.texts.add()
    _stamp(text.timestamp, detection.timestamp_ns)
    text.position.x, text.position.y = detection.u_px + detection.size_px, detection.v_px - detection.size_px
    text.text = label
    text.font_size = 12.0
    text.text_color.r, text.text_color.g, text.text_color.b, text.text_color.a = colour
    return msg


def write_annotated_copy(source: str | os.PathLike, target: str | os.PathLike, report) -> int:
    """Copy ``source`` to ``target`` with the calibration and the detections added; returns messages added."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
    from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    target = Path(target)
    tmp = target.with_name(target.name + ".tmp")
    with open(source, "rb") as src, open(tmp, "wb") as dst:
        writer = Writer(dst, compression=CompressionType.ZSTD)
        writer.start(profile="", library="dronecal-field calibrate --annotate")
        cal_schema = writer.register_schema("foxglove.CameraCalibration", "protobuf", _file_descriptor_set(CameraCalibration))
        ann_schema = writer.register_schema("foxglove.ImageAnnotations", "protobuf", _file_descriptor_set(ImageAnnotations))
        cal_channel = writer.register_channel(CALIBRATION_TOPIC, "protobuf", cal_schema)
        ann_channel = writer.register_channel(ANNOTATIONS_TOPIC, "protobuf", ann_schema)
        # The added messages go in among the run's own by time, so every chunk stays in time order.
        detections = report.detections
        t_first = min((d.timestamp_ns for d in detections), default=int(report.track.t_ns[0]))
        used = {p.window.index for p in report.points if p.used}
        pending = [(t_first, 0, cal_channel, calibration_message(report.camera, t_first).SerializeToString(), 0)]
        pending += [(d.timestamp_ns, 1, ann_channel, annotation_message(d, f"w{g}", g in used).SerializeToString(), seq)
                    for seq, (d, g) in enumerate(zip(detections, report.detection_groups))]
        pending.sort(key=lambda m: (m[0], m[1], m[4]))
        k = 0

        def flush(until_ns: float) -> None:
            nonlocal k
            while k < len(pending) and pending[k][0] <= until_ns:
                t, _, channel, data, seq = pending[k]
                writer.add_message(channel, t, data, t, seq)
                k += 1

        schema_map: dict[int, int] = {}
        channel_map: dict[int, int] = {}
        try:
            for record in StreamReader(src).records:
                if isinstance(record, Schema):
                    if record.id not in schema_map:
                        schema_map[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel):
                    if record.id not in channel_map:
                        channel_map[record.id] = writer.register_channel(
                            record.topic, record.message_encoding, schema_map.get(record.schema_id, 0), dict(record.metadata)
                        )
                elif isinstance(record, Message):
                    if record.channel_id in channel_map:
                        flush(record.log_time)
                        writer.add_message(channel_map[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence)
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                elif isinstance(record, Attachment):
                    writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
                elif isinstance(record, (DataEnd, Footer)):
                    break
        except Exception:  # noqa: BLE001 - mcap raises assorted errors at the damaged end of a cut-off run
            pass
        flush(float("inf"))
        added = len(pending)
        writer.finish()
    os.replace(tmp, target)
    return added
