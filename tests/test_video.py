"""Video sources over real sockets and real files."""

from __future__ import annotations

import http.server
import socket
import struct
import threading
import time

import cv2
import numpy as np
import pytest

from dronecal_field.errors import VideoError
from dronecal_field.video import open_video, read_video_file, video_creation_time_ns


def _jpegs(n: int, w: int = 160, h: int = 120) -> list[bytes]:
    out = []
    for i in range(n):
        img = np.zeros((h, w, 3), np.uint8)
        cv2.putText(img, f"{i:02d}", (20, 80), cv2.FONT_HERSHEY_SIMPLEX, 2.0, (0, 255, 0), 3)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        assert ok
        out.append(buf.tobytes())
    return out


class _MjpegServer:
    """http.server in a thread serving a fixed list of JPEGs as multipart/x-mixed-replace."""

    def __init__(self, jpegs: list[bytes], content_length: bool = True, boundary: str = "frame", content_type: str | None = None):
        self.jpegs = jpegs
        self.connections = 0
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):  # keep test output clean
                pass

            def do_GET(self):
                server.connections += 1
                self.send_response(200)
                self.send_header("Content-Type", content_type or f"multipart/x-mixed-replace; boundary={boundary}")
                self.end_headers()
                try:
                    for data in server.jpegs:
                        head = f"--{boundary}\r\nContent-Type: image/jpeg\r\n"
                        if content_length:
                            head += f"Content-Length: {len(data)}\r\n"
                        self.wfile.write(head.encode() + b"\r\n" + data + b"\r\n")
                        self.wfile.flush()
                        time.sleep(0.005)
                    self.wfile.write(f"--{boundary}--\r\n".encode())
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def _read_all(source, n_max: int) -> list:
    frames = []
    while len(frames) < n_max:
        f = source.read(timeout_s=5.0)
        if f is None:
            break
        frames.append(f)
    return frames


@pytest.mark.parametrize("content_length", [True, False])
def test_mjpeg_passes_jpeg_bytes_through(content_length):
    jpegs = _jpegs(12)
    server = _MjpegServer(jpegs, content_length=content_length)
    try:
        t_before = time.time_ns()
        with open_video(server.url, queue_size=64) as src:
            frames = _read_all(src, 12)
            t_after = time.time_ns()
            assert [f.data for f in frames] == jpegs  # byte-identical, nothing re-encoded
            assert all(f.format == "jpeg" for f in frames)
            stamps = [f.timestamp_ns for f in frames]
            assert stamps == sorted(stamps) and t_before <= stamps[0] and stamps[-1] <= t_after
            assert src.frames_received == 12 and src.frames_dropped == 0
            assert src.bytes_received == sum(len(j) for j in jpegs)
            assert src.read(timeout_s=0.5) is None and src.ended  # the server closed the stream
        decoded = cv2.imdecode(np.frombuffer(frames[5].data, np.uint8), cv2.IMREAD_COLOR)
        assert decoded.shape == (120, 160, 3)
    finally:
        server.close()


def test_mjpeg_reopen_after_stream_ends():
    jpegs = _jpegs(4)
    server = _MjpegServer(jpegs)
    try:
        src = open_video(server.url)
        first = _read_all(src, 4)
        assert src.read(timeout_s=0.5) is None and src.ended
        src.reopen()
        second = _read_all(src, 4)
        src.close()
        assert [f.data for f in first + second] == jpegs + jpegs
        assert src.reconnects == 1 and src.frames_received == 8 and server.connections == 2
    finally:
        server.close()


def test_live_source_drops_oldest_when_consumer_is_slow():
    jpegs = _jpegs(20)
    server = _MjpegServer(jpegs)
    try:
        src = open_video(server.url, queue_size=3)
        deadline = time.monotonic() + 10
        while not src.ended and time.monotonic() < deadline:
            time.sleep(0.02)
        kept = _read_all(src, 20)
        src.close()
        assert src.frames_received == 20
        assert src.frames_dropped == 17 and [f.data for f in kept] == jpegs[-3:]
    finally:
        server.close()


def test_mjpeg_errors_are_video_errors():
    jpegs = _jpegs(1)
    server = _MjpegServer(jpegs, content_type="text/html")
    try:
        with pytest.raises(VideoError, match="not multipart/x-mixed-replace"):
            open_video(server.url)
    finally:
        server.close()
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(VideoError, match="cannot connect"):
        open_video(f"http://127.0.0.1:{port}/x.mjpg", timeout_s=2.0)
    with pytest.raises(VideoError, match=r"scheme 'udp://' is not supported"):
        open_video("udp://127.0.0.1:5600")
    with pytest.raises(VideoError, match="does not exist"):
        open_video("/nonexistent/clip.mp4")


def _write_video(path, n: int, fps: float = 10.0, size=(160, 120)) -> list[np.ndarray]:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    assert writer.isOpened()
    images = []
    for i in range(n):
        img = np.full((size[1], size[0], 3), 20 * i % 250, np.uint8)
        writer.write(img)
        images.append(img)
    writer.release()
    return images


def test_file_source_encodes_every_frame_to_jpeg(tmp_path):
    path = tmp_path / "clip.mp4"
    images = _write_video(path, 15)
    with open_video(str(path)) as src:
        frames = _read_all(src, 100)
    assert len(frames) == 15 and not src.live and src.frames_dropped == 0
    for frame, img in zip(frames, images):
        assert frame.data[:2] == b"\xff\xd8"
        decoded = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
        assert decoded.shape == img.shape
        # mp4v + YUV cost a few grey levels; neighbouring frames differ by 20
        assert abs(float(decoded.mean()) - float(img.mean())) < 6.0


def test_read_video_file_stamps_by_position(tmp_path):
    path = tmp_path / "clip.mp4"
    _write_video(path, 20, fps=10.0)
    start = 1_800_000_000_000_000_000
    got = list(read_video_file(path, start))
    assert [i for i, _, _ in got] == list(range(20))
    assert [f.timestamp_ns - start for _, f, _ in got] == [i * 100_000_000 for i in range(20)]
    assert got[0][2] == (160, 120)
    kept = list(read_video_file(path, start, max_fps=2.5))
    assert [f.timestamp_ns - start for _, f, _ in kept] == [i * 400_000_000 for i in range(5)]


def test_mp4_creation_time(tmp_path):
    path = tmp_path / "clip.mp4"
    _write_video(path, 3)
    assert video_creation_time_ns(path) is None  # OpenCV writes 0 = unknown
    data = bytearray(path.read_bytes())
    i = data.find(b"mvhd")
    assert i > 0 and data[i + 4] == 0  # version 0: 32-bit seconds since 1904
    when_s = 1_800_000_000  # 2027-01-15T08:00:00Z
    data[i + 8 : i + 12] = struct.pack(">I", when_s + 2_082_844_800)
    path.write_bytes(bytes(data))
    assert video_creation_time_ns(path) == when_s * 1_000_000_000
    assert video_creation_time_ns(tmp_path / "missing.mp4") is None
