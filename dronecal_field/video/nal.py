"""H.264 / H.265 access units as pure functions on bytes: NAL units, parameter sets, keyframes.

A camera's own stream is recorded as it arrived (``/camera/video``,
shared/contracts/run-format.md): one Annex B access unit per frame, the
parameter sets (SPS/PPS, and VPS for H.265) in front of every keyframe, no
B-frames. Annex B and length-prefixed (avcC, hvcC) NAL units, parameter sets
from extradata, keyframe tests, a truncation check. No I/O, no PyAV.
"""

from __future__ import annotations

from dataclasses import dataclass

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame

VIDEO_FORMATS = ("h264", "h265")
CODEC_OF_FORMAT = {"h264": "h264", "h265": "hevc"}
FORMAT_OF_CODEC = {"h264": "h264", "hevc": "h265", "h265": "h265"}
START_CODE = b"\x00\x00\x00\x01"

# NAL unit types: parameter sets, keyframe slices, access unit delimiters.
PARAM_TYPES = {"h264": (7, 8), "h265": (32, 33, 34)}
KEY_TYPES = {"h264": (5,), "h265": (16, 17, 18, 19, 20, 21)}  # IDR; H.265 IRAP (BLA, IDR, CRA)
VCL_TYPES = {"h264": range(1, 6), "h265": range(0, 32)}


@dataclass(frozen=True)
class VideoFrame(Frame):
    """One access unit of an H.264 / H.265 stream (``format`` ``h264`` or ``h265``).

    Attributes
    ----------
    keyframe : the access unit starts a GOP (IDR / IRAP) and carries its parameter sets.
    pts_ns : presentation time in the stream's own clock, ns from its first
        frame; None when the source gives none (frames read back from a run).
    """

    keyframe: bool = False
    pts_ns: int | None = None


# --- pure: NAL units ---------------------------------------------------------


def video_format(codec_name: str) -> str:
    """``h264`` / ``h265`` of an FFmpeg codec name; VideoError for anything else."""
    fmt = FORMAT_OF_CODEC.get(codec_name.lower())
    if fmt is None:
        raise VideoError(
            f"the stream is {codec_name}, not H.264 or H.265; set the camera to H.264/H.265, or use its MJPEG stream (http://)"
        )
    return fmt


def nal_type(nal: bytes, fmt: str) -> int:
    """The NAL unit type of one NAL unit (its header first, no start code)."""
    if not nal:
        return -1
    return nal[0] & 0x1F if fmt == "h264" else (nal[0] >> 1) & 0x3F


def split_annexb(data: bytes) -> list[bytes]:
    """NAL units of an Annex B byte stream, start codes (3 or 4 bytes) removed.

    Emulation prevention guarantees ``00 00 01`` never occurs inside a NAL
    unit, so finding start codes finds the units; a trailing zero of a 4-byte
    start code is trimmed from the unit before it.
    """
    out = []
    i = data.find(b"\x00\x00\x01")
    while i >= 0:
        start = i + 3
        j = data.find(b"\x00\x00\x01", start)
        end = len(data) if j < 0 else j
        nal = data[start:end]
        if j >= 0:
            nal = nal.rstrip(b"\x00")  # the leading zero of the next 4-byte start code (trailing_zero_8bits)
        if nal:
            out.append(nal)
        i = j
    return out


def split_length_prefixed(data: bytes, length_size: int) -> list[bytes]:
    """NAL units of an MP4/MKV sample (each unit prefixed by its big-endian length)."""
    out = []
    pos, n = 0, len(data)
    while pos + length_size <= n:
        size = int.from_bytes(data[pos : pos + length_size], "big")
        pos += length_size
        if size <= 0 or pos + size > n:
            break
        out.append(data[pos : pos + size])
        pos += size
    return out


def join_annexb(nals: list[bytes]) -> bytes:
    """An Annex B byte stream of NAL units (4-byte start codes)."""
    return b"".join(START_CODE + n for n in nals)


def parameter_sets(extradata: bytes | None, fmt: str) -> tuple[list[bytes], int | None]:
    """(parameter-set NAL units, NAL length size) of a stream's extradata.

    Extradata is either an ``avcC`` / ``hvcC`` record (MP4, MKV: the samples
    are then length-prefixed with the returned size) or Annex B (RTSP's SDP
    ``sprop-parameter-sets``: size None).
    """
    if not extradata:
        return [], None
    data = bytes(extradata)
    if fmt == "h264" and data[0] == 1 and len(data) >= 7:
        length_size = (data[4] & 0x03) + 1
        nals, pos = [], 5
        count = data[pos] & 0x1F
        pos += 1
        for table in range(2):
            if table == 1:
                if pos >= len(data):
                    break
                count = data[pos]
                pos += 1
            for _ in range(count):
                size = int.from_bytes(data[pos : pos + 2], "big")
                nals.append(data[pos + 2 : pos + 2 + size])
                pos += 2 + size
        return [n for n in nals if n], length_size
    if fmt == "h265" and data[0] == 1 and len(data) >= 23:
        length_size = (data[21] & 0x03) + 1
        nals, pos = [], 23
        for _ in range(data[22]):
            pos += 1  # array_completeness, reserved, NAL_unit_type
            count = int.from_bytes(data[pos : pos + 2], "big")
            pos += 2
            for _ in range(count):
                size = int.from_bytes(data[pos : pos + 2], "big")
                nals.append(data[pos + 2 : pos + 2 + size])
                pos += 2 + size
        return [n for n in nals if n], length_size
    return [n for n in split_annexb(data) if nal_type(n, fmt) in PARAM_TYPES[fmt]], None


def access_unit(
    data: bytes,
    fmt: str,
    keyframe: bool,
    params: list[bytes],
    length_size: int | None = None,
) -> bytes:
    """One access unit in Annex B, the parameter sets in front when it is a keyframe that lacks them.

    Parameters
    ----------
    data : the packet: Annex B (RTSP, .ts, .h264) or length-prefixed (MP4/MKV, ``length_size`` given).
    fmt : ``h264`` or ``h265``.
    keyframe : the packet starts a GOP.
    params : the stream's parameter sets (:func:`parameter_sets`), for keyframes without in-band ones.
    length_size : NAL length size of a length-prefixed packet; None for Annex B.
    """
    if length_size is None:
        if not keyframe or not params:
            return bytes(data)
        nals = split_annexb(bytes(data))
    else:
        nals = split_length_prefixed(bytes(data), length_size)
        if not keyframe or not params:
            return join_annexb(nals)
    types = {nal_type(n, fmt) for n in nals}
    if keyframe and params and not all(nal_type(p, fmt) in types for p in params):
        nals = [n for n in nals if nal_type(n, fmt) not in PARAM_TYPES[fmt]]
        # An access unit delimiter stays first (H.264 7.4.1.2.3).
        head = [n for n in nals[:1] if nal_type(n, fmt) == (9 if fmt == "h264" else 35)]
        nals = head + list(params) + nals[len(head):]
    return join_annexb(nals)


def is_keyframe(data: bytes, fmt: str) -> bool:
    """True when an Annex B access unit holds a keyframe slice (IDR; H.265 IRAP).

    Only the NAL headers up to the first slice are looked at: the start codes
    are found by ``bytes.find``, never a byte loop over a 4K frame.
    """
    key, vcl = KEY_TYPES[fmt], VCL_TYPES[fmt]
    i = data.find(b"\x00\x00\x01")
    while 0 <= i < len(data) - 3:
        t = nal_type(data[i + 3 : i + 4], fmt)
        if t in key:
            return True
        if t in vcl:
            return False
        i = data.find(b"\x00\x00\x01", i + 3)
    return False


def starts_picture(data: bytes, fmt: str) -> bool | None:
    """Whether a packet's first slice is the first slice of a picture (a new access unit); None without a slice.

    H.264: ``first_mb_in_slice`` is 0 (its ue(v) code is the single bit 1, the
    top bit after the one-byte NAL header); H.265:
    ``first_slice_segment_in_pic_flag`` (the top bit after the two-byte
    header). Only the headers up to the first slice are looked at.
    """
    vcl = VCL_TYPES[fmt]
    header = 1 if fmt == "h264" else 2
    i = data.find(b"\x00\x00\x01")
    while 0 <= i < len(data) - 3:
        start = i + 3
        if nal_type(data[start : start + 1], fmt) in vcl:
            if start + header >= len(data):
                return None
            return bool(data[start + header] & 0x80)
        i = data.find(b"\x00\x00\x01", start)
    return None


def video_frame_of(frame: Frame) -> VideoFrame:
    """A Frame read back from ``/camera/video`` as a VideoFrame (keyframe found from its NAL units)."""
    if isinstance(frame, VideoFrame):
        return frame
    return VideoFrame(timestamp_ns=frame.timestamp_ns, format=frame.format, data=frame.data, keyframe=is_keyframe(frame.data, frame.format))


def merge_parts(parts: list[bytes], fmt: str, length_size: int | None = None) -> list[bytes]:
    """NAL units of one access unit delivered in several packets.

    Parameter sets are kept once and only before the first slice (H.264
    7.4.1.2.3: they do not follow the slices of the picture); delimiters
    after the first are dropped.
    """
    nals: list[bytes] = []
    seen_vcl = False
    params_seen: set[bytes] = set()
    for part in parts:
        units = split_annexb(part) if length_size is None else split_length_prefixed(part, length_size)
        for n in units:
            t = nal_type(n, fmt)
            if t in PARAM_TYPES[fmt]:
                if seen_vcl or n in params_seen:
                    continue
                params_seen.add(n)
            elif t == (9 if fmt == "h264" else 35) and nals:
                continue
            elif t in VCL_TYPES[fmt]:
                seen_vcl = True
            nals.append(n)
    return nals
