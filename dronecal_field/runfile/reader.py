"""open_run: stream a run file, complete or cut off, and check it against the contract.

A complete MCAP file ends with a summary (chunk index, channels, metadata
index); a recording killed mid-flight has none and ends inside a chunk. Both
are read the same way: a list of *units* (chunks, or lone messages in an
unchunked file) with their time ranges, taken from the summary when there is
one and otherwise from one cheap linear pass over the record headers that
skips chunk bodies and stops at the first record that runs past the end of the
file. Messages are then decoded one unit at a time, in log-time order, so
memory stays bounded by a few chunks, and time windows only decompress the
chunks that overlap them.

The records are parsed with mcap's own record classes; only the scheduling of
chunks is ours, because mcap's StreamReader cannot skip chunk bodies and
raises assorted errors on a cut-off file.
"""

from __future__ import annotations

import heapq
import io
import json
import math
import os
import re
import stat
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from dronecal_field.errors import ContractError
from dronecal_field.runfile import messages as pm
from dronecal_field.runfile.records import (
    CAMERA_NAME_PATTERN,
    CUT_METADATA_NAME,
    RUN_METADATA_NAME,
    SITE_METADATA_NAME,
    Attitude,
    Frame,
    GnssFix,
    RunEvent,
    RunMetadata,
)

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_ATTACHMENT, _OP_METADATA, _OP_DATA_END = 0x09, 0x0C, 0x0F

# The contract's required topics and their schema names.
REQUIRED_TOPICS = {pm.IMAGE_TOPIC: pm.IMAGE_SCHEMA, pm.FIX_TOPIC: pm.FIX_SCHEMA}
# ... where /camera/video (the camera's H.264/H.265 stream) may stand in for /camera/image.
CAMERA_TOPICS = {pm.IMAGE_TOPIC: pm.IMAGE_SCHEMA, pm.VIDEO_TOPIC: pm.VIDEO_SCHEMA}
OPTIONAL_TOPICS = {pm.ATTITUDE_TOPIC: pm.ATTITUDE_SCHEMA, pm.EVENTS_TOPIC: pm.EVENT_SCHEMA}
# A several-camera run: /cameras/<name>/image or /cameras/<name>/video per camera, instead of /camera/...
CAMERAS_PREFIX = "/cameras/"
_CAMERA_TOPIC = re.compile(r"/cameras/(?P<name>[^/]*)/(?P<kind>image|video)\Z")
CAMERA_KIND_SCHEMAS = {"image": pm.IMAGE_SCHEMA, "video": pm.VIDEO_SCHEMA}


def camera_topic_of(name: str, kind: str = "image") -> str:
    """The topic of camera ``name`` in a several-camera run: ``/cameras/<name>/image`` (or ``video``)."""
    return f"{CAMERAS_PREFIX}{name}/{kind}"

# Frames are selected by MCAP log time first (cheap, per chunk), then by the
# message's own timestamp. A writer whose log time lags capture by more than
# this would lose frames at window edges.
LOG_TIME_SLACK_NS = 1_000_000_000

# A /camera/video frame decodes from the keyframe before it: a window is read
# from this long before its start. Cameras send a keyframe every 1-4 s; a GOP
# longer than this leaves the first frames of a window undecodable (counted).
KEYFRAME_LOOKBACK_NS = 10_000_000_000


@dataclass(frozen=True)
class _Unit:
    """A chunk, or a lone message record, of the data section."""

    offset: int  # file offset of the record's opcode byte
    length: int  # record body length, bytes
    start_ns: int
    end_ns: int
    channel_ids: frozenset[int] | None  # from the chunk index; None when unknown


@dataclass(frozen=True)
class _Channel:
    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str


def open_run(path: str | os.PathLike, camera: str | None = None) -> "Run":
    """Open and check a run file; use as a context manager.

    Parameters
    ----------
    path : the .mcap run file.
    camera : in a several-camera run (``/cameras/<name>/...``), the camera whose frames
        ``iter_frames`` reads and whose size and latency ``metadata`` carries; None: the
        first of metadata ``cameras``. Must be None for a one-camera run.

    Returns
    -------
    Run
        with ``metadata``, ``truncated`` and the ``iter_*`` methods.

    Raises
    ------
    ContractError
        when the file is not MCAP, lacks the ``dronecal.run`` metadata or a key
        of it, or lacks ``/camera/image`` / ``/gnss/fix`` with their schemas.
    InputError
        when the file cannot be read.

    Examples
    --------
    >>> with open_run("run.mcap") as run:          # doctest: +SKIP
    ...     for fix in run.iter_fixes(): ...
    """
    return Run(path, camera)


class Run:
    """An open run file. Not thread-safe: iterate from one thread.

    Attributes
    ----------
    path : the file.
    metadata : the parsed ``dronecal.run`` (+ ``dronecal.site``) metadata.
    truncated : True when the file has no valid end (cut off, killed writer):
        only the complete chunks before the damage are read.
    truncated_at : byte offset where readable data ends when truncated, else None.
    topics : topic -> schema name of every channel seen.
    warnings : problems that do not stop calibration (e.g. an optional topic
        with the wrong schema, which is then ignored).
    units_read : chunks (or lone message records) decoded so far; shows how
        much of the file a windowed read touched.
    """

    def __init__(self, path: str | os.PathLike, camera: str | None = None) -> None:
        from dronecal_field.errors import InputError

        self.path = Path(path)
        self._want_camera = camera
        self.camera_topics: dict[str, str] = {}  # camera name -> its topic, in a several-camera run
        self._name = self.path.name
        try:
            mode = os.stat(self.path).st_mode
        except OSError as exc:
            raise InputError(f"cannot open run file {self.path}: {exc.strerror}") from exc
        if not stat.S_ISREG(mode):  # opening a FIFO waits for a writer for ever; a device never ends
            raise InputError(f"run file {self.path} is not a regular file (a {'folder' if stat.S_ISDIR(mode) else 'pipe or device'}): give the .mcap file")
        try:
            self._f = open(self.path, "rb")
        except OSError as exc:
            raise InputError(f"cannot open run file {self.path}: {exc.strerror}") from exc
        try:
            self._size = os.fstat(self._f.fileno()).st_size
            self.truncated = False
            self.truncated_at: int | None = None
            self.warnings: list[str] = []
            self.recording_stopped: str | None = None  # the writer's own note of an early stop (a full disk)
            self.undecodable: dict[str, int] = {}  # topic -> messages whose payload did not decode (skipped)
            self.damaged_spans: set[tuple[int, int, int]] = set()  # (byte offset, start_ns, end_ns) of chunks skipped
            self.units_read = 0
            self._events: list[RunEvent] | None = None  # /events, once read
            self._units: list[_Unit] = []
            self._channels: dict[int, _Channel] = {}
            self._schemas: dict[int, tuple[str, str]] = {}  # id -> (name, encoding)
            self._metadata: dict[str, dict[str, str]] = {}
            self._attachments: list[tuple[str, int]] = []  # (name, record offset)
            self._open()
            self.metadata = self._check_contract()
            self._check_frame_size()
        except BaseException:
            self._f.close()
            raise

    # -- context manager ---------------------------------------------------

    def __enter__(self) -> "Run":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._f.close()

    # -- public reading ------------------------------------------------------

    @property
    def time_range_ns(self) -> tuple[int, int] | None:
        """(first, last) message log time in the readable part of the file, UTC ns; None when empty."""
        if not self._units:
            return None
        return min(u.start_ns for u in self._units), max(u.end_ns for u in self._units)

    @property
    def units_total(self) -> int:
        """Number of chunks (or lone message records) in the readable part of the file."""
        return len(self._units)

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> schema name of every channel known so far."""
        return {c.topic: c.schema_name for c in self._channels.values()}

    def metadata_record(self, name: str) -> dict[str, str] | None:
        """Any MCAP metadata record by name (the last one when repeated), or None."""
        record = self._metadata.get(name)
        return dict(record) if record is not None else None

    @property
    def gnss_stamping(self) -> tuple[str, float | None]:
        """How ``/gnss/fix`` is stamped: ``("fix_time", None)`` as the contract says, or
        ``("arrival", latency_s)`` when the writer declared metadata ``gnss.latency_s``
        (its latency estimate in seconds, None when ``unknown``).
        """
        text = self.metadata.extra.get("gnss.latency_s")
        if text is None:
            return "fix_time", None
        try:
            value = float(text)
        except ValueError:
            return "arrival", None
        return "arrival", (value if math.isfinite(value) else None)

    def _decode(self, topic: str, decode: Callable[[bytes, int], Any], data: bytes, log_time: int) -> Any:
        """A message decoded, or None when its payload does not decode: skipped and counted, like a damaged chunk."""
        try:
            return decode(data, log_time)
        except Exception:  # noqa: BLE001 - any payload that is not the schema's message
            self.undecodable[topic] = self.undecodable.get(topic, 0) + 1
            self._warn_once(f"messages on {topic} that do not decode as its schema are skipped (counted in undecodable)")
            return None

    def iter_fixes(self) -> Iterator[GnssFix]:
        """GNSS fixes of ``/gnss/fix`` in log-time order (a payload that does not decode is skipped and counted)."""
        for _, data, log_time in self._iter_topic({pm.FIX_TOPIC}):
            fix = self._decode(pm.FIX_TOPIC, pm.fix_from_bytes, data, log_time)
            if fix is not None:
                yield fix

    @property
    def video(self) -> bool:
        """True when the frames are the camera's H.264/H.265 stream (``/camera/video``), not images."""
        return self.camera_topic.endswith("/video")

    @property
    def cameras(self) -> tuple[str, ...]:
        """Names of the cameras of a several-camera run, in metadata order; () for a one-camera run."""
        return tuple(self.camera_topics)

    @property
    def camera(self) -> str | None:
        """The camera this Run reads frames of in a several-camera run; None in a one-camera run."""
        return self.metadata.camera_name

    def iter_frames(self, windows: list[tuple[int, int]] | None = None) -> Iterator[Frame]:
        """Video frames of ``/camera/image`` (or the access units of ``/camera/video``) in log-time order.

        Parameters
        ----------
        windows : optional [start_ns, end_ns] ranges (inclusive, UTC ns); only
            frames whose timestamp lies in one of them are returned, and only
            chunks overlapping them (with LOG_TIME_SLACK_NS) are read. For
            ``/camera/video`` each window also returns the access units from
            the keyframe before its start (within KEYFRAME_LOOKBACK_NS), which
            a decoder needs first; their frames are ``VideoFrame`` with
            ``keyframe`` set (dronecal_field.video.nal).
        """
        topic = self.camera_topic
        decode = pm.frame_from_video_bytes if self.video else pm.frame_from_bytes
        if windows is None:
            for _, data, log_time in self._iter_topic({topic}):
                frame = self._decode(topic, decode, data, log_time)
                if frame is not None:
                    yield frame
            return
        merged = _merge_windows(windows)
        if not merged:
            return
        lookback = KEYFRAME_LOOKBACK_NS if self.video else 0
        wide = _merge_windows([(a - LOG_TIME_SLACK_NS - lookback, b + LOG_TIME_SLACK_NS) for a, b in merged])
        starts = [a for a, _ in merged]
        import bisect

        def inside(t: int) -> bool:
            i = bisect.bisect_right(starts, t) - 1
            return i >= 0 and t <= merged[i][1]

        if not self.video:
            for _, data, log_time in self._iter_topic({topic}, wide):
                frame = self._decode(topic, decode, data, log_time)
                if frame is not None and inside(frame.timestamp_ns):
                    yield frame
            return
        from dronecal_field.video.nal import video_frame_of

        # Outside the windows, only the access units since the last keyframe are kept: the
        # run-up a decoder needs to reach a window's first frame.
        run_up: list[Frame] = []
        for _, data, log_time in self._iter_topic({topic}, wide):
            raw = self._decode(topic, decode, data, log_time)
            if raw is None:
                continue
            frame = video_frame_of(raw)
            if inside(frame.timestamp_ns):
                yield from run_up
                run_up = []
                yield frame
            elif frame.keyframe:
                run_up = [frame]
            elif run_up:
                run_up.append(frame)

    def iter_events(self) -> Iterator[RunEvent]:
        """Events of ``/events`` (hover windows and other marks) in log-time order.

        Read once and kept (a few hundred small records): the stages that ask for them (hover windows, legs,
        clock jumps) would otherwise each pass over every chunk that carries one, i.e. most of the file.
        """
        if self._events is None:
            if not self._has_topic(pm.EVENTS_TOPIC):
                self._events = []
            else:
                decoded = (self._decode(pm.EVENTS_TOPIC, pm.event_from_bytes, data, log_time) for _, data, log_time in self._iter_topic({pm.EVENTS_TOPIC}))
                self._events = [e for e in decoded if e is not None]
        yield from self._events

    def iter_attitude(self) -> Iterator[Attitude]:
        """Vehicle attitude from ``/vehicle/attitude``, else from ``/mavlink/ATTITUDE``."""
        if self._has_topic(pm.ATTITUDE_TOPIC):
            for _, data, log_time in self._iter_topic({pm.ATTITUDE_TOPIC}):
                att = self._decode(pm.ATTITUDE_TOPIC, pm.attitude_from_bytes, data, log_time)
                if att is not None:
                    yield att
            return
        for _, t_ns, fields in self.iter_mavlink({"ATTITUDE"}):
            try:
                yield Attitude(
                    timestamp_ns=t_ns,
                    roll_rad=float(fields["roll"]),
                    pitch_rad=float(fields["pitch"]),
                    yaw_rad=float(fields["yaw"]),
                )
            except (KeyError, TypeError, ValueError):
                continue  # a malformed optional message is skipped, not fatal

    def iter_mavlink(self, names: set[str] | None = None) -> Iterator[tuple[str, int, dict[str, Any]]]:
        """Raw MAVLink messages of ``/mavlink/<NAME>`` topics in log-time order.

        Parameters
        ----------
        names : message names to return (e.g. ``{"GPS_RAW_INT"}``); None for all.

        Yields
        ------
        (name, timestamp_ns, fields) : ``timestamp_ns`` is ``_time_unix_ns``
            when the message has it, else its log time.
        """
        prefix = pm.MAVLINK_TOPIC_PREFIX
        if names is None:
            wanted: Callable[[str], bool] = lambda topic: topic.startswith(prefix)  # noqa: E731
        else:
            topics = {prefix + n for n in names}
            wanted = topics.__contains__
        for topic, data, log_time in self._iter_topic(wanted):
            try:
                fields = json.loads(data)
            except ValueError:
                continue
            if not isinstance(fields, dict):
                continue
            t_ns = fields.get("_time_unix_ns")
            yield topic[len(prefix):], int(t_ns) if isinstance(t_ns, int) else log_time, fields

    def attachment(self, name: str) -> bytes | None:
        """The data of the last attachment with this name (e.g. ``mission.plan``), or None."""
        from mcap.data_stream import ReadDataStream
        from mcap.records import Attachment

        for att_name, offset in reversed(self._attachments):
            if att_name != name:
                continue
            body = self._read_record_body(offset)
            if body is None:
                return None
            # MCAP closes an attachment with a CRC-32 of all its other fields (0: not computed).
            stored = int.from_bytes(body[-4:], "little") if len(body) >= 4 else 0
            if stored and zlib.crc32(body[:-4]) != stored:
                self._warn_once(f"attachment {name} at byte {offset} is damaged (CRC mismatch): ignored")
                return None
            try:
                return Attachment.read(ReadDataStream(io.BytesIO(body))).data
            except Exception:  # noqa: BLE001 - a damaged record, as a damaged chunk
                self._warn_once(f"attachment {name} at byte {offset} is damaged: ignored")
                return None
        return None

    def _warn_once(self, text: str) -> None:
        if text not in self.warnings:
            self.warnings.append(text)

    # -- opening -----------------------------------------------------------

    def _open(self) -> None:
        self._f.seek(0)
        if self._f.read(8) != MAGIC:
            raise ContractError(f"{self._name}: not an MCAP file (no MCAP magic at the start); give a .mcap run file")
        if not self._open_from_summary():
            self._scan()

    def _open_from_summary(self) -> bool:
        """Use the summary section when the file is complete and has a chunk index."""
        from mcap.data_stream import ReadDataStream
        from mcap.exceptions import McapError
        from mcap.reader import SeekingReader
        from mcap.records import Metadata

        if self._size < 8 + 9 + 20 + 8:
            return False
        self._f.seek(-8, io.SEEK_END)
        if self._f.read(8) != MAGIC:
            return False
        try:
            self._f.seek(0)
            summary = SeekingReader(self._f).get_summary()
        except (McapError, struct.error, ValueError, EOFError):
            return False
        if summary is None or not summary.chunk_indexes or not summary.channels:
            return False
        if not self._data_end_precedes_summary():
            return False  # a summary that does not belong to this data section (runs joined with cat): the scan decides
        if any(ch.schema_id and ch.schema_id not in summary.schemas for ch in summary.channels.values()):
            return False  # channels without their schemas: the data section has both
        for sid, s in summary.schemas.items():
            self._schemas[sid] = (s.name, s.encoding)
        for ch in summary.channels.values():
            self._add_channel(ch.id, ch.topic, ch.message_encoding, ch.schema_id)
        for ci in summary.chunk_indexes:
            self._units.append(
                _Unit(
                    offset=ci.chunk_start_offset,
                    length=ci.chunk_length - 9,
                    start_ns=ci.message_start_time,
                    end_ns=ci.message_end_time,
                    channel_ids=frozenset(ci.message_index_offsets) or None,
                )
            )
        for ai in summary.attachment_indexes:
            self._attachments.append((ai.name, ai.offset))
        if summary.metadata_indexes:
            for mi in summary.metadata_indexes:
                body = self._read_record_body(mi.offset)
                if body is not None:
                    md = Metadata.read(ReadDataStream(io.BytesIO(body)))
                    self._metadata[md.name] = dict(md.metadata)
        else:
            # A summary without a metadata index: metadata lives outside chunks, a header pass finds it.
            self._units.clear()
            self._attachments.clear()
            self._scan()
        return True

    def _check_frame_size(self) -> None:
        """Metadata camera.width/height against the first frame's own size: the frames win, with a warning."""
        from dataclasses import replace

        topic = self.camera_topic
        if topic.endswith("/video") or self.metadata.width is None:
            return
        for _, data, log_time in self._iter_topic({topic}):
            frame = self._decode(topic, pm.frame_from_bytes, data, log_time)
            if frame is None:
                continue
            size = image_size(frame.data)
            if size is not None and size != (self.metadata.width, self.metadata.height):
                key = "camera.width x height" if self.camera is None else f"camera.{self.camera}.width x height"
                self.warnings.append(
                    f"metadata {key} = {self.metadata.width}x{self.metadata.height} but the frames are "
                    f"{size[0]}x{size[1]}: the frames' size is used (fix the writer's metadata)")
                self.metadata = replace(self.metadata, width=size[0], height=size[1])
            return

    def _data_end_precedes_summary(self) -> bool:
        """The footer's summary starts right after a DataEnd record, as in a file written as one."""
        f = self._f
        f.seek(self._size - 8 - 29)
        footer = f.read(29)
        if len(footer) < 29 or footer[0] != _OP_FOOTER:
            return False
        summary_start = struct.unpack("<Q", footer[9:17])[0]
        if summary_start < 8 + 13 or summary_start > self._size:
            return False
        f.seek(summary_start - 13)
        head = f.read(9)
        return len(head) == 9 and head[0] == _OP_DATA_END and struct.unpack("<Q", head[1:9])[0] == 4

    def _scan(self) -> None:
        """One pass over record headers: units, metadata, attachments, top-level channels.

        Chunk bodies are skipped (only their 28-byte time header is read). The
        pass stops at DataEnd/Footer, or at the first record that does not fit
        in the file, which marks the file as truncated.
        """
        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel, Message, Metadata, Schema

        f = self._f
        pos = 8
        complete = False
        while True:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                break
            opcode, length = struct.unpack("<BQ", head)
            body_at = pos + 9
            if body_at + length > self._size:
                break
            if opcode == _OP_CHUNK:
                if length < 28:
                    break
                start_ns, end_ns = struct.unpack("<QQ", f.read(16))
                self._units.append(_Unit(offset=pos, length=length, start_ns=start_ns, end_ns=end_ns, channel_ids=None))
            elif opcode in (_OP_DATA_END, _OP_FOOTER):
                complete = True
                self._refuse_a_second_run(pos)
                break
            elif opcode in (_OP_METADATA, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
                try:
                    stream = ReadDataStream(io.BytesIO(f.read(length)))
                    if opcode == _OP_METADATA:
                        md = Metadata.read(stream)
                        self._metadata[md.name] = dict(md.metadata)
                    elif opcode == _OP_SCHEMA:
                        s = Schema.read(stream)
                        self._schemas[s.id] = (s.name, s.encoding)
                    elif opcode == _OP_CHANNEL:
                        ch = Channel.read(stream)
                        self._add_channel(ch.id, ch.topic, ch.message_encoding, ch.schema_id)
                    else:
                        msg = Message.read(stream, length)
                        self._units.append(
                            _Unit(
                                offset=pos,
                                length=length,
                                start_ns=msg.log_time,
                                end_ns=msg.log_time,
                                channel_ids=frozenset([msg.channel_id]),
                            )
                        )
                except Exception:  # noqa: BLE001 - any damage ends the readable part
                    break
            elif opcode == _OP_ATTACHMENT:
                name = self._attachment_name(body_at)
                if name is not None:
                    self._attachments.append((name, pos))
            pos = body_at + length
        if not complete:
            self.truncated = True
            self.truncated_at = pos

    def _refuse_a_second_run(self, data_end_at: int) -> None:
        """A file that goes on after its own end with another MCAP file (two runs joined with ``cat``): refused.

        Reads from this run's DataEnd to the end of the file (its summary, a few kB, for a single run).
        """
        f = self._f
        f.seek(data_end_at)
        block = 1 << 20
        offset = data_end_at
        tail = b""
        while True:
            chunk = f.read(block)
            if not chunk:
                return
            buf = tail + chunk
            start = 0
            while (i := buf.find(MAGIC, start)) >= 0:
                at = offset - len(tail) + i
                if at + len(MAGIC) < self._size:  # not this file's closing magic: more follows
                    raise ContractError(
                        f"{self._name}: a second MCAP file starts at byte {at} (two runs joined, e.g. with cat); "
                        "give each run as its own file (calibrate a.mcap b.mcap pools them into one camera)")
                start = i + 1
            tail = buf[-(len(MAGIC) - 1):]
            offset += len(chunk)

    def _attachment_name(self, body_at: int) -> str | None:
        # Attachment body: log_time u64, create_time u64, name (u32 length + utf-8), ...
        self._f.seek(body_at + 16)
        raw = self._f.read(4)
        if len(raw) < 4:
            return None
        (n,) = struct.unpack("<I", raw)
        try:
            return self._f.read(n).decode("utf-8")
        except UnicodeDecodeError:
            return None

    def _add_channel(self, cid: int, topic: str, encoding: str, schema_id: int) -> None:
        name, schema_encoding = self._schemas.get(schema_id, ("", ""))
        self._channels[cid] = _Channel(cid, topic, encoding, name, schema_encoding)

    def _check_contract(self) -> RunMetadata:
        cut = f" (the file is cut off at byte {self.truncated_at})" if self.truncated else ""
        run_md = self._metadata.get(RUN_METADATA_NAME)
        if run_md is None:
            raise ContractError(
                f"{self._name}: no metadata record '{RUN_METADATA_NAME}'{cut}; the writer must store "
                "format_version, camera.width/height and marker.* (docs/runfile.md)"
            )
        metadata = RunMetadata.from_mcap_metadata(run_md, self._metadata.get(SITE_METADATA_NAME), source=self._name)
        self._listed = metadata.camera_names()
        if not self._has_camera() or not self._has_topic(pm.FIX_TOPIC):
            self._discover_channels()
        if metadata.cameras or any(c.topic.startswith(CAMERAS_PREFIX) for c in self._channels.values()):
            metadata = self._check_cameras(metadata, cut)
        elif self._want_camera is not None:
            from dronecal_field.errors import InputError

            raise InputError(f"{self._name} is a one-camera run (/camera/...): it has no camera {self._want_camera!r}; leave the camera out")
        if not self.camera_topics and self._has_topic(pm.IMAGE_TOPIC) and self._has_topic(pm.VIDEO_TOPIC):
            raise ContractError(
                f"{self._name}: both '{pm.IMAGE_TOPIC}' and '{pm.VIDEO_TOPIC}'; a run has one camera topic: "
                "write the frames to one of them"
            )
        if self.camera_topics:
            camera = self.camera_topic
        else:
            camera = pm.VIDEO_TOPIC if self._has_topic(pm.VIDEO_TOPIC) else pm.IMAGE_TOPIC
            self.camera_topic = camera
        for topic in ([] if self.camera_topics else [camera]) + [pm.FIX_TOPIC]:
            schema = CAMERA_TOPICS.get(topic) or REQUIRED_TOPICS[topic]
            channels = [c for c in self._channels.values() if c.topic == topic]
            if not channels:
                what = "video frames" if topic == pm.IMAGE_TOPIC else "GNSS fixes"
                name = f"'{topic}' ({schema}) or '{pm.VIDEO_TOPIC}' ({pm.VIDEO_SCHEMA})" if topic == pm.IMAGE_TOPIC else f"'{topic}' ({schema})"
                raise ContractError(
                    f"{self._name}: no topic {name}{cut}: the run has no {what}; "
                    "record them, or build a run from a flight log with `dronecal-field import`"
                )
            for c in channels:
                if c.schema_name != schema or c.message_encoding != "protobuf":
                    raise ContractError(
                        f"{self._name}: topic '{topic}' has schema '{c.schema_name}' "
                        f"({c.message_encoding or 'no'} encoding); the contract needs '{schema}' in protobuf"
                    )
        for topic, schema in OPTIONAL_TOPICS.items():
            for c in self._channels.values():
                if c.topic == topic and (c.schema_name != schema or c.message_encoding != "protobuf"):
                    self.warnings.append(
                        f"topic '{topic}' has schema '{c.schema_name}', not '{schema}' in protobuf: ignored"
                    )
        stopped = self._metadata.get(CUT_METADATA_NAME)
        if stopped is not None:
            self.recording_stopped = stopped.get("reason") or "stopped early"
            self.warnings.append(f"the recording stopped early ({self.recording_stopped}): the run ends there")
        return metadata

    def _check_cameras(self, metadata: RunMetadata, cut: str) -> RunMetadata:
        """A several-camera run: each listed camera has one topic of the contract's schema, nothing else; the
        metadata of the chosen camera (``open_run(camera=...)``, else the first)."""
        from dronecal_field.errors import InputError

        single = [t for t in (pm.IMAGE_TOPIC, pm.VIDEO_TOPIC) if self._has_topic(t)]
        multi = sorted({c.topic for c in self._channels.values() if c.topic.startswith(CAMERAS_PREFIX)})
        if single and (multi or metadata.cameras):
            what = f"topics {multi[0]} and {single[0]}" if multi else f"metadata 'cameras' and topic {single[0]}"
            raise ContractError(
                f"{self._name}: {what}: a run has either one camera on /camera/... or several on /cameras/<name>/..., "
                "not both: write every camera under /cameras/<name>/ (and list it in 'cameras')"
            )
        if not metadata.cameras:
            raise ContractError(
                f"{self._name}: topic {multi[0]} but the '{RUN_METADATA_NAME}' metadata has no 'cameras': list the camera "
                "names (comma separated) with camera.<name>.width/height for each"
            )
        topics: dict[str, list[str]] = {}
        for topic in multi:
            m = _CAMERA_TOPIC.match(topic)
            if m is None or not re.fullmatch(CAMERA_NAME_PATTERN, m["name"]):
                raise ContractError(
                    f"{self._name}: topic {topic!r} is not /cameras/<name>/image or /cameras/<name>/video with a name of "
                    "1-32 of a-z, 0-9, '_', '-': rename the camera"
                )
            if m["name"] not in self._listed:
                raise ContractError(
                    f"{self._name}: topic {topic} is of camera {m['name']!r}, which metadata 'cameras' "
                    f"({', '.join(self._listed)}) does not list: add it to 'cameras' with its camera.{m['name']}.width/height"
                )
            topics.setdefault(m["name"], []).append(topic)
        for name in self._listed:
            have = topics.get(name, [])
            if not have:
                raise ContractError(
                    f"{self._name}: camera {name!r} is listed in 'cameras' but has no topic {camera_topic_of(name)} or "
                    f"{camera_topic_of(name, 'video')}{cut}: record its frames, or leave it out of 'cameras'"
                )
            if len(have) > 1:
                raise ContractError(f"{self._name}: camera {name!r} has both {have[0]} and {have[1]}: write its frames to one of them")
            kind = _CAMERA_TOPIC.match(have[0])["kind"]
            schema = CAMERA_KIND_SCHEMAS[kind]
            for c in self._channels.values():
                if c.topic == have[0] and (c.schema_name != schema or c.message_encoding != "protobuf"):
                    raise ContractError(
                        f"{self._name}: topic '{c.topic}' has schema '{c.schema_name}' ({c.message_encoding or 'no'} encoding); "
                        f"the contract needs '{schema}' in protobuf"
                    )
            self.camera_topics[name] = have[0]
        name = self._want_camera if self._want_camera is not None else self._listed[0]
        if name not in self.camera_topics:
            raise InputError(f"{self._name} has no camera {name!r}: its cameras are {', '.join(self._listed)}")
        self.camera_topic = self.camera_topics[name]
        return metadata.for_camera(name)

    def _discover_channels(self) -> None:
        """Decompress units in file order until the channels of GNSS fixes and a camera topic are known."""
        for unit in sorted(self._units, key=lambda u: u.offset):
            self._read_unit(unit)
            if self._has_topic(pm.FIX_TOPIC) and self._has_camera():
                return

    def _has_camera(self) -> bool:
        """A camera topic is known: /camera/..., or in a several-camera run one for each listed camera."""
        listed = getattr(self, "_listed", ())
        if listed:
            known = {c.topic for c in self._channels.values()}
            return all(camera_topic_of(n) in known or camera_topic_of(n, "video") in known for n in listed)
        return self._has_topic(pm.IMAGE_TOPIC) or self._has_topic(pm.VIDEO_TOPIC)

    def _has_topic(self, topic: str) -> bool:
        return any(c.topic == topic for c in self._channels.values())

    def _good_channel(self, c: _Channel) -> bool:
        m = _CAMERA_TOPIC.match(c.topic) if c.topic.startswith(CAMERAS_PREFIX) else None
        schema = (REQUIRED_TOPICS.get(c.topic) or CAMERA_TOPICS.get(c.topic) or OPTIONAL_TOPICS.get(c.topic)
                  or (CAMERA_KIND_SCHEMAS[m["kind"]] if m else None))
        return schema is None or (c.schema_name == schema and c.message_encoding == "protobuf")

    # -- unit reading --------------------------------------------------------

    def _read_record_body(self, offset: int) -> bytes | None:
        self._f.seek(offset)
        head = self._f.read(9)
        if len(head) < 9:
            return None
        _, length = struct.unpack("<BQ", head)
        body = self._f.read(length)
        return body if len(body) == length else None

    def _read_unit(self, unit: _Unit) -> list[Any]:
        """Messages of one unit; channel and schema records inside it are registered."""
        from mcap.data_stream import ReadDataStream
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import breakup_chunk

        self._f.seek(unit.offset)
        head = self._f.read(9)
        if len(head) < 9:
            return []
        opcode, length = struct.unpack("<BQ", head)
        body = self._f.read(length)
        if len(body) < length:
            return []
        self.units_read += 1
        stream = ReadDataStream(io.BytesIO(body))
        if opcode == _OP_MESSAGE:
            return [Message.read(stream, length)]
        try:
            records = breakup_chunk(Chunk.read(stream), validate_crc=True)
        except Exception:  # noqa: BLE001 - a damaged chunk is skipped, as if cut off
            self.warnings.append(f"damaged chunk at byte {unit.offset} skipped")
            self.damaged_spans.add((unit.offset, unit.start_ns, unit.end_ns))
            return []
        out = []
        for rec in records:
            if isinstance(rec, Message):
                out.append(rec)
            elif isinstance(rec, Schema):
                self._schemas[rec.id] = (rec.name, rec.encoding)
            elif isinstance(rec, Channel):
                if rec.id not in self._channels:
                    self._add_channel(rec.id, rec.topic, rec.message_encoding, rec.schema_id)
        return out

    def _iter_topic(
        self,
        topics: set[str] | Callable[[str], bool],
        windows: list[tuple[int, int]] | None = None,
    ) -> Iterator[tuple[str, bytes, int]]:
        """(topic, data, log_time_ns) of messages on the wanted topics, merged in log-time order.

        Units are loaded in order of their start time; a message is released
        once no unit still to be loaded can start before it (mcap's own
        ordering rule), so memory holds only the units that overlap in time.
        """
        wanted = topics.__contains__ if isinstance(topics, (set, frozenset)) else topics

        def overlaps(u: _Unit) -> bool:
            if windows is None:
                return True
            return any(u.start_ns <= b and a <= u.end_ns for a, b in windows)

        def may_hold(u: _Unit) -> bool:
            if u.channel_ids is None:
                return True
            for cid in u.channel_ids:
                c = self._channels.get(cid)
                if c is None or wanted(c.topic):
                    return True
            return False

        def in_windows(t: int) -> bool:
            return windows is None or any(a <= t <= b for a, b in windows)

        units = sorted((u for u in self._units if overlaps(u) and may_hold(u)), key=lambda u: (u.start_ns, u.offset))
        heap: list[tuple[int, int, int, str, bytes]] = []
        serial = 0
        i = 0
        while i < len(units) or heap:
            if i < len(units) and (not heap or units[i].start_ns <= heap[0][0]):
                for msg in self._read_unit(units[i]):
                    c = self._channels.get(msg.channel_id)
                    if c is None or not wanted(c.topic) or not self._good_channel(c):
                        continue
                    if not in_windows(msg.log_time):
                        continue
                    heapq.heappush(heap, (msg.log_time, serial, msg.channel_id, c.topic, msg.data))
                    serial += 1
                i += 1
            else:
                log_time, _, _, topic, data = heapq.heappop(heap)
                yield topic, data, log_time


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF or a PNG's IHDR header, without decoding; None if neither."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and i + 9 <= n:
            height, width = struct.unpack(">HH", data[i + 5:i + 9])
            return int(width), int(height)
        i += 2 + length
    return None


def _merge_windows(windows: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """Sorted, non-overlapping union of [start, end] windows (empty ones dropped)."""
    out: list[list[int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in windows if b >= a):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]
