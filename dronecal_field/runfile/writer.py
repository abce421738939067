"""RunWriter: record a run into one MCAP file that survives being cut off.

Crash safety is the point of this module. MCAP keeps messages in chunks and a
reader can only use complete chunks, so a chunk is closed (and the file
flushed and fsync'ed) when it is ``max_chunk_age_s`` old, by the next write or
by a background flusher when no write comes. The ``dronecal.run`` metadata and
the channels of the required topics are written at open, so a recording
killed with SIGKILL keeps everything up to about one second before the kill
and still passes the contract check (docs/runfile.md).

Thread-safety: every public method takes one lock, so a writer may be shared
by several threads; the intended use is one writer thread fed by queues.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dronecal_field.errors import InputError, RecordingStoppedError
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.runfile import messages as pm
from dronecal_field.runfile.records import (
    RUN_METADATA_NAME,
    SITE_METADATA_NAME,
    Attitude,
    Frame,
    GnssFix,
    RunEvent,
    RunMetadata,
    site_to_metadata,
)

IMAGE_FORMATS = ("jpeg", "png")
VIDEO_FORMATS = ("h264", "h265")
CAMERA_TOPICS = ("image", "video")
COMPRESSIONS = ("zstd", "lz4", "none")
CAMERA_NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,31}"  # the contract's "Several cameras in one run"
CAMERAS_TOPIC_PREFIX = "/cameras/"
# The single camera's keys, absent from a several-camera run (each camera has its own camera.<name>.*).
_SINGLE_CAMERA_KEYS = ("camera.width", "camera.height", "camera.latency_s", "camera.clock", "camera.timestamps", "camera.rtcp_to_arrival_s")


@dataclass(frozen=True)
class RunCamera:
    """One camera of a several-camera run (contract: "Several cameras in one run").

    Attributes
    ----------
    name : matches ``[a-z0-9][a-z0-9_-]{0,31}``; its topic is ``/cameras/<name>/<topic>``.
    topic : ``"image"`` (JPEG/PNG) or ``"video"`` (H.264/H.265 access units).
    width, height : image size, pixels.
    latency_s : capture-to-stamp delay of its frames, seconds; None when unknown.
    clock : how its frames are stamped (``rtcp``, ``arrival``, ``file``), or None.
    extra : further ``camera.<name>.<key>`` metadata (e.g. ``url``), kept verbatim.
    """

    name: str
    topic: str
    width: int
    height: int
    latency_s: float | None = None
    clock: str | None = None
    extra: dict[str, str] = field(default_factory=dict)

    @property
    def topic_name(self) -> str:
        return f"{CAMERAS_TOPIC_PREFIX}{self.name}/{self.topic}"

    def metadata(self) -> dict[str, str]:
        """Its ``camera.<name>.*`` keys of ``dronecal.run``."""
        key = f"camera.{self.name}."
        out = {key + k: str(v) for k, v in self.extra.items()}
        out[key + "width"] = str(int(self.width))
        out[key + "height"] = str(int(self.height))
        out[key + "latency_s"] = "unknown" if self.latency_s is None else repr(float(self.latency_s))
        if self.clock is not None:
            out[key + "clock"] = self.clock
        return out


def check_camera_name(name: str) -> str | None:
    """Why ``name`` cannot name a camera of a run (None when it can)."""
    if re.fullmatch(CAMERA_NAME_PATTERN, name or ""):
        return None
    return (f"camera name {name!r} is not [a-z0-9][a-z0-9_-]{{0,31}} (lower-case letters, digits, '_' and '-', "
            "at most 32, starting with a letter or digit)")


def several_cameras_metadata(metadata: RunMetadata, cameras: "list[RunCamera] | tuple[RunCamera, ...]") -> dict[str, str]:
    """The ``dronecal.run`` record of a several-camera run: ``cameras`` in order and each one's ``camera.<name>.*``;
    no ``camera.width``/``camera.height`` (nor the single camera's other keys)."""
    out = {k: v for k, v in metadata.to_mcap_metadata().items() if k not in _SINGLE_CAMERA_KEYS}
    out["cameras"] = ",".join(c.name for c in cameras)
    for cam in cameras:
        out.update(cam.metadata())
    return out


class _WholeWrites:
    """An unbuffered file for mcap's Writer: each ``write`` lands whole or raises (a partial write of a
    full disk is retried, then ENOSPC raised), and ``tell`` is exact, so the last good end is known."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.pos = 0
        self.closed = False

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self.fd, view)
            if n <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            self.pos += n
            view = view[n:]
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def fileno(self) -> int:
        return self.fd

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            os.close(self.fd)


def _jsonable(value: Any) -> Any:
    """JSON-safe copy: bytes become lists of ints, NaN/inf become null (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "item"):  # numpy scalars
        return _jsonable(value.item())
    return value


def _json_schema(name: str, fields: dict[str, Any]) -> bytes:
    """A small JSON Schema (titled ``name``) of a message's fields, so Foxglove can plot them."""

    def kind(v: Any) -> str:
        if isinstance(v, bool):
            return "boolean"
        if isinstance(v, (int, float)) or v is None:
            return "number"
        if isinstance(v, str):
            return "string"
        if isinstance(v, (list, tuple, bytes, bytearray)):
            return "array"
        return "object"

    props = {k: {"type": kind(v)} for k, v in fields.items()}
    schema = {"title": name, "type": "object", "properties": props}
    return json.dumps(schema, separators=(",", ":")).encode()


class RunWriter:
    """Write a run file (shared/contracts/run-format.md) with crash-safe chunking.

    Parameters
    ----------
    path : output .mcap path (overwritten).
    metadata : the run's metadata; written at open as ``dronecal.run`` (and
        ``dronecal.site`` when it has a site origin).
    compression : ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    chunk_size : close a chunk once it holds this many bytes (uncompressed).
    max_chunk_age_s : close a chunk at the latest this many seconds after its
        first message, so a killed process loses at most about this much.
    background_flush : run a flusher thread that closes an old chunk even when
        no further write arrives.
    camera : ``"image"`` (``/camera/image``, JPEG/PNG frames, the default) or
        ``"video"`` (``/camera/video``, H.264/H.265 access units passed through):
        a run has one of them, registered at open.
    cameras : several cameras (:class:`RunCamera`, in order) instead of ``camera``:
        ``/cameras/<name>/image|video`` each, the ``cameras`` and
        ``camera.<name>.*`` metadata, no ``/camera/...`` topic and no
        ``camera.width``/``camera.height`` (``metadata.width``/``height`` unused).

    Examples
    --------
    >>> with RunWriter("run.mcap", meta) as w:          # doctest: +SKIP
    ...     w.write_fix(fix); w.write_frame(frame)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        metadata: RunMetadata,
        compression: str = "zstd",
        chunk_size: int = 1 << 20,
        max_chunk_age_s: float = 1.0,
        background_flush: bool = True,
        camera: str = "image",
        cameras: "list[RunCamera] | tuple[RunCamera, ...] | None" = None,
    ) -> None:
        from mcap.writer import CompressionType, Writer
        from mcap.well_known import MessageEncoding

        if compression not in COMPRESSIONS:
            raise InputError(f"compression {compression!r} unknown; use one of {', '.join(COMPRESSIONS)}")
        if camera not in CAMERA_TOPICS:
            raise InputError(f"camera {camera!r} unknown; use image (/camera/image) or video (/camera/video)")
        self.camera = camera
        self.cameras = {c.name: c for c in cameras} if cameras else None
        if cameras:
            for cam in cameras:
                if (why := check_camera_name(cam.name)) is not None:
                    raise InputError(why)
                if cam.topic not in CAMERA_TOPICS:
                    raise InputError(f"camera {cam.name}: topic {cam.topic!r} unknown; use image or video")
            if len(self.cameras) != len(cameras):
                raise InputError(f"camera names repeat ({', '.join(c.name for c in cameras)}): give each camera its own name")
        if max_chunk_age_s <= 0:
            raise InputError(f"max_chunk_age_s = {max_chunk_age_s} must be positive")
        self.path = Path(path)
        self.metadata = metadata
        self.max_chunk_age_s = float(max_chunk_age_s)
        self.messages_written = 0
        self._lock = threading.Lock()
        self._closed = False
        self._chunk_started: float | None = None  # monotonic time of the first message in the open chunk
        self._good_end = 0  # bytes of the file known complete (after the last chunk written whole)
        self.failure: str | None = None  # why writing stopped (a full disk), once it has
        self.cut_ns: int | None = None  # UTC ns of the last message in the file when writing stopped
        self._last_synced_ns: int | None = None
        self._last_added_ns: int | None = None
        try:
            self._file = _WholeWrites(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666))
        except OSError as exc:
            raise InputError(f"cannot create run file {self.path}: {exc.strerror}; check the directory") from exc
        try:
            self._mcap = Writer(
                self._file,
                chunk_size=int(chunk_size),
                compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
                    compression
                ],
            )
            from dronecal_field import __version__

            self._mcap.start(profile="", library=f"dronecal-field/{__version__}")
            self._protobuf = MessageEncoding.Protobuf
            self._channels: dict[str, int] = {}
            record = several_cameras_metadata(metadata, cameras) if cameras else metadata.to_mcap_metadata()
            self._mcap.add_metadata(RUN_METADATA_NAME, record)
            site = metadata.site_metadata()
            if site is not None:
                self._mcap.add_metadata(SITE_METADATA_NAME, site)
            # Registered now so the first chunk written carries them, whatever comes first.
            from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
            from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
            from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

            if cameras:
                for cam in cameras:
                    self._proto_channel(cam.topic_name, CompressedVideo if cam.topic == "video" else CompressedImage)
            elif camera == "video":
                self._proto_channel(pm.VIDEO_TOPIC, CompressedVideo)
            else:
                self._proto_channel(pm.IMAGE_TOPIC, CompressedImage)
            self._proto_channel(pm.FIX_TOPIC, LocationFix)
            self._write_channels_outside_chunks()
            self._sync_locked()
            self._fsync()
        except (OSError, RecordingStoppedError) as exc:
            self._file.close()
            why = self.failure or (exc.strerror if isinstance(exc, OSError) else str(exc))
            raise InputError(f"cannot write the run file {self.path} ({why}): free some space or choose another disk") from None
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None
        if background_flush:
            self._flusher = threading.Thread(target=self._flush_loop, name="runfile-flush", daemon=True)
            self._flusher.start()

    # -- context manager -------------------------------------------------

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writing -----------------------------------------------------------

    def write_frame(self, frame: Frame, camera: str | None = None) -> None:
        """Write one video frame (log time = the frame's timestamp).

        A JPEG/PNG frame goes to ``/camera/image``; an H.264/H.265 access unit
        (Annex B) to ``/camera/video``, whichever the writer was opened for.
        In a several-camera run, ``camera`` names the camera: its own topic
        ``/cameras/<camera>/image|video`` (frame_id ``<camera>``).
        """
        if self.cameras is not None:
            cam = self.cameras.get(camera or "")
            if cam is None:
                raise InputError(f"camera {camera!r} is not one of this run's ({', '.join(self.cameras)}); name one of them")
            video = cam.topic == "video"
            if frame.format not in (VIDEO_FORMATS if video else IMAGE_FORMATS):
                raise InputError(f"frame format {frame.format!r} on {cam.topic_name}; give {'h264 or h265' if video else 'jpeg or png'} frames")
            message = pm.video_frame_to_proto(frame) if video else pm.frame_to_proto(frame)
            message.frame_id = cam.name
            self._write_proto(cam.topic_name, message, frame.timestamp_ns)
            return
        if camera is not None:
            raise InputError(f"camera {camera!r} named in a single-camera run; open the writer with cameras=[...]")
        if self.camera == "video":
            if frame.format not in VIDEO_FORMATS:
                raise InputError(
                    f"frame format {frame.format!r} in a /camera/video run; give h264 or h265 access units, or open the writer with camera='image'"
                )
            self._write_proto(pm.VIDEO_TOPIC, pm.video_frame_to_proto(frame), frame.timestamp_ns)
            return
        if frame.format not in IMAGE_FORMATS:
            raise InputError(
                f"frame format {frame.format!r} is not an image format; encode as jpeg or png, or open the writer with camera='video' for h264/h265"
            )
        self._write_proto(pm.IMAGE_TOPIC, pm.frame_to_proto(frame), frame.timestamp_ns)

    def write_fix(self, fix: GnssFix) -> None:
        """Write one GNSS fix on ``/gnss/fix``."""
        self._write_proto(pm.FIX_TOPIC, pm.fix_to_proto(fix), fix.timestamp_ns)

    def write_attitude(self, att: Attitude) -> None:
        """Write one attitude on ``/vehicle/attitude`` (foxglove.PoseInFrame, FLU in ENU)."""
        self._write_proto(pm.ATTITUDE_TOPIC, pm.attitude_to_proto(att), att.timestamp_ns)

    def write_event(self, event: RunEvent) -> None:
        """Write one event on ``/events`` (foxglove.Event; log time = the event start), and as a line of
        ``/events/log`` (foxglove.Log), which the Foxglove app's Log panel shows."""
        self._write_proto(pm.EVENTS_TOPIC, pm.event_to_proto(event), event.timestamp_ns)
        self._write_proto(pm.EVENTS_LOG_TOPIC, pm.event_to_log(event), event.timestamp_ns)

    def write_mavlink(self, name: str, timestamp_ns: int, fields: dict[str, Any]) -> None:
        """Write one MAVLink message on ``/mavlink/<name>`` as JSON (schema ``mavlink.<name>``).

        Parameters
        ----------
        name : the message name, e.g. ``"GPS_RAW_INT"``.
        timestamp_ns : its time on the run clock, UTC ns (also ``_time_unix_ns``).
        fields : the message's fields as pymavlink's ``to_dict()`` gives them;
            ``mavpackettype`` is dropped, bytes become lists, NaN becomes null.
        """
        self.write_json(pm.MAVLINK_TOPIC_PREFIX + name, f"mavlink.{name}", timestamp_ns, fields)

    def write_json(self, topic: str, schema_name: str, timestamp_ns: int, fields: dict[str, Any]) -> None:
        """Write one JSON message (with ``_time_unix_ns``) on any topic, e.g. ``/dataflash/GPS``."""
        body = {k: v for k, v in fields.items() if k != "mavpackettype"}
        body["_time_unix_ns"] = int(timestamp_ns)
        try:
            data = json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError):
            data = json.dumps(_jsonable(body), separators=(",", ":"), allow_nan=False).encode()
        with self._lock:
            self._check_open()
            channel = self._channels.get(topic)
            if channel is None:
                schema = self._mcap.register_schema(
                    name=schema_name, encoding="jsonschema", data=_json_schema(schema_name, body)
                )
                channel = self._mcap.register_channel(topic=topic, message_encoding="json", schema_id=schema)
                self._channels[topic] = channel
            synced = self._add_locked(channel, int(timestamp_ns), data)
        if synced:
            self._fsync()

    def attach(self, name: str, data: bytes, media_type: str) -> None:
        """Store a file (e.g. ``mission.plan``) as an MCAP attachment, written and synced at once."""
        now = time.time_ns()
        with self._lock:
            self._check_open()
            self._guarded(lambda: self._mcap.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=bytes(data)))
        self._fsync()

    def write_site(self, origin: EnuOrigin) -> None:
        """Store the ENU origin for reports as metadata ``dronecal.site``, written and synced at once."""
        with self._lock:
            self._check_open()
            self._guarded(lambda: self._mcap.add_metadata(SITE_METADATA_NAME, site_to_metadata(origin)))
        self._fsync()

    def flush(self) -> None:
        """Close the open chunk, flush and fsync: everything written so far survives a crash."""
        with self._lock:
            if self._closed or self.failure is not None:
                return
            self._sync_locked()
        self._fsync()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self._flusher is not None:
            self._stop.set()
            self._flusher.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                if self.failure is None:
                    try:
                        self._mcap.finish()
                    except OSError as exc:
                        self._fail_locked(exc)
                if self.failure is not None:
                    self._finish_cut_locked()
                self._fsync()
            finally:
                self._file.close()

    # -- internals ---------------------------------------------------------

    def _proto_channel(self, topic: str, message_class: Any) -> int:
        from mcap_protobuf.schema import register_schema

        channel = self._channels.get(topic)
        if channel is None:
            schema = register_schema(self._mcap, message_class)
            channel = self._mcap.register_channel(topic=topic, message_encoding=self._protobuf, schema_id=schema)
            self._channels[topic] = channel
        return channel

    def _write_channels_outside_chunks(self) -> None:
        """The schemas and channels registered so far, also as records of their own at the top of the file.

        mcap's Writer puts them into the first chunk, so a disk that fills before that chunk is written
        would leave a run without its camera and GNSS topics; top-level copies (identical records, as
        MCAP allows) make even a run cut at its first chunk name its topics.
        """
        from mcap.data_stream import RecordBuilder

        schemas = getattr(self._mcap, "_Writer__schemas", {})
        channels = getattr(self._mcap, "_Writer__channels", {})
        builder = RecordBuilder()
        for schema in schemas.values():
            schema.write(builder)
        for channel in channels.values():
            channel.write(builder)
        self._file.write(builder.end())

    def _write_proto(self, topic: str, message: Any, log_time_ns: int) -> None:
        data = message.SerializeToString()
        with self._lock:
            self._check_open()
            channel = self._proto_channel(topic, type(message))
            synced = self._add_locked(channel, int(log_time_ns), data)
        if synced:
            self._fsync()

    def _add_locked(self, channel: int, log_time_ns: int, data: bytes) -> bool:
        """Add a message; close the chunk when it is old. True when the caller should fsync."""
        self._guarded(lambda: self._mcap.add_message(channel_id=channel, log_time=log_time_ns, data=data, publish_time=log_time_ns))
        self.messages_written += 1
        self._last_added_ns = max(self._last_added_ns or log_time_ns, log_time_ns)
        now = time.monotonic()
        if self._chunk_started is None:
            self._chunk_started = now
        elif now - self._chunk_started >= self.max_chunk_age_s:
            self._sync_locked()
            return True
        return False

    def _sync_locked(self) -> None:
        # mcap's flush() closes the chunk in progress and flushes the stream.
        self._guarded(self._mcap.flush)
        self._chunk_started = None
        self._good_end = self._file.tell()
        self._last_synced_ns = self._last_added_ns

    def _guarded(self, write: Any) -> None:
        """Run one write into the file; a full disk (any OSError) stops the writer for good, keeping the
        file up to its last complete chunk, and raises RecordingStoppedError."""
        if self.failure is not None:
            raise RecordingStoppedError(self.failure)
        try:
            write()
        except OSError as exc:
            self._fail_locked(exc)
            raise RecordingStoppedError(self.failure) from None

    def _fail_locked(self, exc: OSError) -> None:
        """Cut the file back to its last complete chunk (freeing what a full disk half wrote)."""
        if self.failure is not None:
            return
        why = "disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else (exc.strerror or str(exc))
        self.cut_ns = self._last_synced_ns
        self.failure = f"{why} at byte {self._good_end} of {self.path}: writing stopped; the run keeps what was written before"
        try:
            os.ftruncate(self._file.fd, self._good_end)
            os.lseek(self._file.fd, self._good_end, os.SEEK_SET)
        except OSError:
            pass
        self._file.pos = self._good_end

    def _finish_cut_locked(self) -> None:
        """End a cut file validly: a metadata record stating the cut, DataEnd and a footer with no summary
        (readers scan the data section). If even that does not fit, the file stays cut at a chunk end,
        which the run reader also reads (it states the cut)."""
        from mcap.data_stream import RecordBuilder
        from mcap.records import DataEnd, Footer, Metadata

        from dronecal_field.runfile.records import CUT_METADATA_NAME

        cut = {"reason": self.failure or "", "cut_at_byte": str(self._good_end),
               "last_message_ns": str(self.cut_ns) if self.cut_ns is not None else "none"}
        for with_note in (True, False):
            builder = RecordBuilder()
            if with_note:
                Metadata(name=CUT_METADATA_NAME, metadata=cut).write(builder)
            DataEnd(0).write(builder)
            Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
            tail = builder.end() + b"\x89MCAP0\r\n"
            try:
                os.lseek(self._file.fd, self._good_end, os.SEEK_SET)
                self._file.pos = self._good_end
                self._file.write(tail)
                return
            except OSError:
                try:
                    os.ftruncate(self._file.fd, self._good_end)
                except OSError:
                    return

    def _fsync(self) -> None:
        try:
            os.fsync(self._file.fileno())
        except (OSError, ValueError):
            pass  # closed meanwhile, or a file system without fsync: the flush already reached the OS

    def _flush_loop(self) -> None:
        period = self.max_chunk_age_s / 4.0
        while not self._stop.wait(period):
            synced = False
            with self._lock:
                if self._closed or self.failure is not None:
                    return
                started = self._chunk_started
                if started is not None and time.monotonic() - started >= self.max_chunk_age_s:
                    try:
                        self._sync_locked()
                    except RecordingStoppedError:
                        return  # said by the next write (and by close): never a thread's traceback
                    synced = True
            if synced:
                self._fsync()

    def _check_open(self) -> None:
        if self._closed:
            raise InputError(f"run file {self.path} is closed; open a new RunWriter to write more")
