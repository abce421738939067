"""What the simulated RTSP camera costs per frame at 4K: rendering, I420, and the H.264/H.265 encoders.

Run by hand (``make rtsp-deps`` first)::

    .venv/bin/python benchmarks/bench_sim_camera_rates.py                 # 3840x2160, 50 frames
    .venv/bin/python benchmarks/bench_sim_camera_rates.py --size 1920x1080 --frames 100

The demo's camera at the asked size (focal scaled with the width); the drone
flies in from 30 m to 5 m along the optical axis. Reported, as CPU time per
frame (user + system; on a shared machine wall time says more about the
neighbours than about the code) and as the cores that 25 fps would need:

- ``render_in_place`` (the stream's path: frozen noised background, only the
  drone's box redrawn, adaptive supersampling) against ``render`` (a fresh
  full-frame copy and full-frame noise, the MJPEG tests' path);
- BGR -> I420 (OpenCV, as RtspOut sends it);
- each encoder on those I420 frames from a file (``gst-launch-1.0 filesrc !
  rawvideoparse ! x265enc/x264enc ! fakesink``; CPU of the child), with the
  options ``sim camera`` uses (ultrafast, zerolatency, no B-frames, a
  keyframe every 2 s, ~0.1 bit per pixel) and, for x265, constant QP 32.

Measured 2026-11-27 (2 cores, load average 11-29 from other sessions), 4K:
render_in_place 5.1 ms (drone 18-30 m), 8.4 ms (8-17 m), 19.5 ms (5-7 m)
against render's 21-34 ms; I420 7 ms; x265 (bitrate mode) ~205 ms, x265 QP 32
~134 ms, x264 ~42 ms (each BGR-input figure from gst-launch minus its 33 ms
videoconvert). 4K25 H.265 then needs 3.4-5 cores for the encoder alone, 4K25
H.264 ~1.2 cores plus the rest: neither runs in real time on 2 cores beside
``fly``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def child_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def main() -> int:
    import cv2
    import numpy as np

    from dronecal_field.core.camera import Distortion
    from dronecal_field.demo import MARKER, SITE, TRUTH
    from dronecal_field.geodesy import EnuOrigin
    from dronecal_field.sim.render import FrameRenderer
    from dronecal_field.sim.scene import MarkerSpec, VehiclePose, make_truth_camera

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="3840x2160")
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--fps", type=int, default=25)
    args = p.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    scale = width / TRUTH["width"]
    origin = EnuOrigin(SITE["lat"], SITE["lon"], SITE["ground_h"])
    cam = make_truth_camera(origin, SITE["mount_height"], SITE["azimuth"], SITE["tilt"], TRUTH["focal_px"] * scale, width, height,
                            distortion=Distortion(k1=TRUTH["k1"], k2=TRUTH["k2"], p1=TRUTH["p1"], p2=TRUTH["p2"]))
    marker = MarkerSpec(dictionary=MARKER["dictionary"], marker_id=MARKER["marker_id"], size_m=MARKER["size_m"], offset_frd_m=MARKER["offset_frd_m"])
    print(f"load average {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)", flush=True)
    c0 = time.process_time()
    renderer = FrameRenderer(cam, marker, noise_sigma_dn=2.0, seed=0)
    print(f"renderer set-up (ray map, background): {time.process_time() - c0:.1f} s CPU", flush=True)
    centre, R = cam.pose.position_world, np.asarray(cam.pose.R_cam_from_world)
    poses = []
    for k in range(args.frames):
        dist = 30.0 - 25.0 * k / max(1, args.frames - 1)
        ant = centre + R.T @ np.array([0.1 * dist * np.sin(k / 10), 0.1 * dist, dist])
        poses.append(VehiclePose(antenna_enu_m=ant, yaw_rad=float(np.arctan2(centre[0] - ant[0], centre[1] - ant[1]))))

    raw = Path(tempfile.mkdtemp(prefix="bench-simcam-")) / "frames.i420"
    cost = {"render_in_place": 0.0, "render": 0.0, "i420": 0.0}
    with raw.open("wb") as f:
        for v in poses:
            c0 = time.process_time()
            img = renderer.render_in_place(v)
            c1 = time.process_time()
            yuv = cv2.cvtColor(img, cv2.COLOR_BGR2YUV_I420)
            c2 = time.process_time()
            cost["render_in_place"] += c1 - c0
            cost["i420"] += c2 - c1
            f.write(yuv.tobytes())
    for v in poses:
        c0 = time.process_time()
        renderer.render(v)
        cost["render"] += time.process_time() - c0
    n = len(poses)
    for name, s in cost.items():
        print(f"{name}: {1e3 * s / n:.1f} ms CPU a frame ({s / n * args.fps:.2f} cores at {args.fps} fps)", flush=True)

    gop, kbps = 2 * args.fps, max(500, int(0.1 * width * height * args.fps / 1000))
    encoders = {
        "x265 (sim camera's)": f"x265enc tune=zerolatency speed-preset=ultrafast key-int-max={gop} bitrate={kbps} option-string=bframes=0:repeat-headers=1:aud=0",
        "x265 QP 32": f"x265enc tune=zerolatency speed-preset=ultrafast key-int-max={gop} qp=32 option-string=bframes=0:repeat-headers=1:aud=0",
        "x264 (sim camera's)": f"x264enc tune=zerolatency speed-preset=ultrafast bframes=0 key-int-max={gop} bitrate={kbps} byte-stream=true",
    }
    frame_bytes = width * height * 3 // 2
    for name, enc in encoders.items():
        c0 = child_cpu_s()
        t0 = time.monotonic()
        cmd = (f"gst-launch-1.0 -q filesrc location={raw} blocksize={frame_bytes} ! rawvideoparse width={width} height={height} "
               f"format=i420 framerate={args.fps}/1 ! {enc} ! fakesink")
        done = subprocess.run(cmd, shell=True, capture_output=True, text=True)
        s = child_cpu_s() - c0
        status = "" if done.returncode == 0 else f" (exit {done.returncode}: {done.stderr.strip()[-200:]})"
        print(f"{name}: {1e3 * s / n:.1f} ms CPU a frame ({s / n * args.fps:.2f} cores at {args.fps} fps), "
              f"{time.monotonic() - t0:.1f} s wall{status}", flush=True)
    raw.unlink()
    raw.parent.rmdir()
    print(f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
