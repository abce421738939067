"""Regenerate the replays: record the demo chain, shrink each run to a few MB, write its truth.

Each replay is a real recording: ``dronecal_field.demo.run_demo`` runs plan,
``sim vehicle``, ``sim camera`` (MJPEG over HTTP) and ``fly --start`` in their
own processes, and ``fly`` records run.mcap. That file (150 MB at 1280x720)
is then rewritten through ``RunWriter`` as a contract run a test can afford:

* frames downscaled by 2 (``cv2.INTER_AREA``), re-encoded as JPEG (quality 75),
  and only a few per hover window: the ``--hold-frames`` nearest the middle of
  each hold, plus every second frame of ``--transitions`` moves between holds
  (the motion the time alignment needs). Frames are chosen by capture time, that is
  the stamp minus the camera latency the simulator was given, so the hold
  frames show the hold whatever the latency; every kept frame is within 0.4 s
  of a hover window;
* every ``/gnss/fix``, ``/events`` and ``/vehicle/attitude`` message; the MAVLink
  topics a reviewer plots, the fast ones thinned to 5 Hz (``MAVLINK_THIN_HZ``);
* the ``dronecal.run`` metadata with ``camera.width/height`` halved, the site,
  the ``mission.plan`` attachment.

Downscaling by 2 changes the true camera exactly: fx, fy halve and
c' = (c + 0.5) / 2 - 0.5 (OpenCV pixel centres); distortion and pose are
unchanged. That camera is written beside each replay as ``<name>.truth.yaml``,
and ``replays.json`` lists every replay with its truth and sizes.

Usage (about 2.5 min per recorded replay)::

    .venv/bin/python replays/make_replays.py            # all, into replays/
    .venv/bin/python replays/make_replays.py --work /tmp/rec --keep-recordings
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronecal_field.core.camera import Camera, Intrinsics

HERE = Path(__file__).resolve().parent

# A 0.4 s margin around each hold: frames further from every hold show the
# drone in transit and are never needed (the contract's offset bound is
# covered by selecting on capture time instead).
MARGIN_S = 0.4
# The MAVLink topics kept, and those thinned (rates on the run clock: the
# simulator at speed-up 3 sends ATTITUDE and GLOBAL_POSITION_INT at 30 Hz,
# GPS_RAW_INT at 15 Hz, MISSION_CURRENT at 6 Hz; /gnss/fix and
# /vehicle/attitude keep every sample, so these copies are for plots only).
MAVLINK_KEEP = ("HEARTBEAT", "GPS_RAW_INT", "ATTITUDE", "MISSION_ITEM_REACHED", "MISSION_CURRENT",
                "GLOBAL_POSITION_INT", "STATUSTEXT")
MAVLINK_THIN_HZ = {"ATTITUDE": 5.0, "GLOBAL_POSITION_INT": 5.0, "GPS_RAW_INT": 5.0, "MISSION_CURRENT": 1.0}


@dataclass(frozen=True)
class ReplaySpec:
    """One replay to record.

    Attributes
    ----------
    name : file stem in replays/ (``<name>.mcap``, ``<name>.truth.yaml``).
    latency_s : ``sim camera --latency-s``: frames show the vehicle this late, seconds.
    what : one line for the README and replays.json.
    """

    name: str
    latency_s: float
    what: str


RECORDED = (
    ReplaySpec("nominal", 0.0, "the demo: distorted 1280x720 camera on a 4 m pole, RTK fixed, no camera latency"),
    ReplaySpec("latency", 0.5, "as nominal, but the camera's frames show the vehicle 0.5 s late (sim camera --latency-s 0.5)"),
)
# The cut-off replay: the shrunk nominal run cut at this fraction of its bytes
# (plus an odd offset, so the cut falls inside a record, not between two).
CUT_FRACTION = 0.55
CUT_ODD_BYTES = 777


def half_resolution(camera: Camera) -> Camera:
    """The true camera of frames downscaled by 2 with area averaging.

    Pixel (u', v') of the half image covers pixels 2u'..2u'+1 of the full one,
    so its centre is at full-image u = 2u' + 0.5: u' = (u + 0.5) / 2 - 0.5.
    Focal lengths halve; distortion (on normalised coordinates) and pose are unchanged.

    Parameters
    ----------
    camera : the full-resolution camera; width and height must be even.
    """
    i = camera.intrinsics
    if i.width % 2 or i.height % 2:
        raise ValueError(f"image size {i.width}x{i.height} is not even: a factor-2 downscale would not be exact")
    half = Intrinsics(
        fx=i.fx / 2.0, fy=i.fy / 2.0, cx=(i.cx + 0.5) / 2.0 - 0.5, cy=(i.cy + 0.5) / 2.0 - 0.5,
        width=i.width // 2, height=i.height // 2,
    )
    return camera.with_(intrinsics=half, covariance=None)


def select_frames(
    stamps_ns: np.ndarray,
    windows_ns: np.ndarray,
    latency_s: float,
    hold_frames: int,
    transitions: int,
    transition_step: int = 2,
) -> np.ndarray:
    """Indices of the frames a replay keeps (sorted).

    Parameters
    ----------
    stamps_ns : (F,) int64 frame stamps, run clock.
    windows_ns : (W, 2) int64 hover windows [start, end], GNSS clock, in time order.
    latency_s : the camera's known latency: capture time = stamp - latency.
    hold_frames : frames kept per window, those whose capture time is nearest the window's middle.
    transitions : moves between consecutive windows kept (the frames from
        0.1 s before one window ends to 0.1 s after the next starts), spread
        evenly over the flight.
    transition_step : keep every this many frames of a transition (2 at 15 fps
        still gives the time alignment a moving detection every 0.13 s).

    Returns
    -------
    (K,) int indices into ``stamps_ns``.
    """
    capture = np.asarray(stamps_ns, np.int64) - int(round(latency_s * 1e9))
    windows_ns = np.asarray(windows_ns, np.int64).reshape(-1, 2)
    keep: set[int] = set()
    for start, end in windows_ns:
        middle = (start + end) // 2
        inside = np.flatnonzero((capture >= start) & (capture <= end))
        nearest = inside[np.argsort(np.abs(capture[inside] - middle), kind="stable")[:hold_frames]]
        keep.update(int(k) for k in nearest)
    n_gaps = len(windows_ns) - 1
    if transitions > 0 and n_gaps > 0:
        # Evenly spread, away from the first and last move.
        picks = np.unique(np.round(np.linspace(0, n_gaps - 1, transitions + 2)[1:-1]).astype(int))
        edge = int(0.1e9)
        for k in picks:
            a, b = windows_ns[k, 1] - edge, windows_ns[k + 1, 0] + edge
            keep.update(int(j) for j in np.flatnonzero((capture >= a) & (capture <= b))[::transition_step])
    margin = int(MARGIN_S * 1e9)
    near = [j for j in keep if np.any((capture[j] >= windows_ns[:, 0] - margin) & (capture[j] <= windows_ns[:, 1] + margin))]
    return np.array(sorted(near), dtype=int)


def thin_times(t_ns: np.ndarray, rate_hz: float) -> np.ndarray:
    """(N,) bool: keep a message when at least 1/rate_hz has passed since the last kept one."""
    keep = np.zeros(len(t_ns), bool)
    last = None
    period = int(1e9 / rate_hz)
    for k, t in enumerate(np.asarray(t_ns, np.int64)):
        if last is None or t - last >= period * 0.95:  # 5 % slack for jitter in the stream
            keep[k] = True
            last = t
    return keep


@dataclass(frozen=True)
class ShrinkReport:
    """What ``shrink_run`` kept."""

    frames_in: int
    frames_kept: int
    windows: int
    fixes: int
    events: int
    attitudes: int
    mavlink: dict[str, int]
    bytes_out: int


def shrink_run(
    src: Path,
    dst: Path,
    latency_s: float,
    hold_frames: int = 3,
    transitions: int = 4,
    transition_step: int = 2,
    jpeg_quality: int = 75,
    chunk_size: int = 128 << 10,
) -> ShrinkReport:
    """Rewrite the recorded run ``src`` as a small contract run ``dst`` (see the module docstring).

    Parameters
    ----------
    latency_s : the camera latency the recording was made with, seconds (selects hold frames).
    chunk_size : MCAP chunk size, bytes; small chunks let a cut-off file keep most of its prefix.
    """
    import cv2
    from dataclasses import replace

    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import Frame
    from dronecal_field.runfile.writer import RunWriter

    with open_run(src) as run:
        md = run.metadata
        events = list(run.iter_events())
        windows = np.array(
            [(e.timestamp_ns, e.end_ns) for e in events if e.type == "hover"], np.int64
        ).reshape(-1, 2)
        windows = windows[np.argsort(windows[:, 0])]
        stamps = np.array([f.timestamp_ns for f in run.iter_frames()], np.int64)
        chosen = set(stamps[select_frames(stamps, windows, latency_s, hold_frames, transitions, transition_step)].tolist())
        half_w, half_h = md.width // 2, md.height // 2
        frames = []
        for f in run.iter_frames([(t, t) for t in sorted(chosen)]):
            img = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
            small = cv2.resize(img, (half_w, half_h), interpolation=cv2.INTER_AREA)
            ok, jpg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality, cv2.IMWRITE_JPEG_OPTIMIZE, 1])
            if not ok:
                raise RuntimeError(f"JPEG encoding failed for the frame at {f.timestamp_ns}")
            frames.append(Frame(timestamp_ns=f.timestamp_ns, format="jpeg", data=jpg.tobytes()))
        fixes = list(run.iter_fixes())
        attitudes = list(run.iter_attitude())
        mavlink: dict[str, list[tuple[int, dict]]] = {}
        for name, t_ns, fields in run.iter_mavlink(set(MAVLINK_KEEP)):
            mavlink.setdefault(name, []).append((t_ns, fields))
        mission = run.attachment("mission.plan")

    for name, rate in MAVLINK_THIN_HZ.items():
        if name in mavlink:
            keep = thin_times(np.array([t for t, _ in mavlink[name]], np.int64), rate)
            mavlink[name] = [m for m, k in zip(mavlink[name], keep) if k]

    extra = dict(md.extra)
    extra["replay.source"] = f"dronecal-field demo (fly --start on sim vehicle + sim camera), {md.width}x{md.height}"
    extra["replay.shrink"] = (
        f"replays/make_replays.py: frames /2 (INTER_AREA, JPEG q{jpeg_quality}), {hold_frames} per hover window "
        f"+ every {transition_step}. frame of {transitions} transitions; MAVLink {','.join(MAVLINK_KEEP)}"
    )
    meta = replace(md, width=half_w, height=half_h, extra=extra)

    # One time-ordered stream: chunks then cover contiguous time, so a cut file keeps a clean prefix.
    stream: list[tuple[int, int, str, object]] = []
    stream += [(f.timestamp_ns, 0, "frame", f) for f in frames]
    stream += [(x.timestamp_ns, 1, "fix", x) for x in fixes]
    stream += [(a.timestamp_ns, 2, "attitude", a) for a in attitudes]
    stream += [(e.timestamp_ns, 3, "event", e) for e in events]
    for name, msgs in mavlink.items():
        stream += [(t, 4, "mavlink", (name, t, fields)) for t, fields in msgs]
    stream.sort(key=lambda r: (r[0], r[1]))

    dst.parent.mkdir(parents=True, exist_ok=True)
    with RunWriter(dst, meta, chunk_size=chunk_size, max_chunk_age_s=3600.0, background_flush=False) as w:
        if mission is not None:
            w.attach("mission.plan", mission, "application/json")  # first, so a cut file keeps it
        for _, _, kind, item in stream:
            if kind == "frame":
                w.write_frame(item)
            elif kind == "fix":
                w.write_fix(item)
            elif kind == "attitude":
                w.write_attitude(item)
            elif kind == "event":
                w.write_event(item)
            else:
                name, t, fields = item
                w.write_mavlink(name, t, fields)
    return ShrinkReport(
        frames_in=len(stamps), frames_kept=len(frames), windows=len(windows), fixes=len(fixes), events=len(events),
        attitudes=len(attitudes), mavlink={k: len(v) for k, v in sorted(mavlink.items())}, bytes_out=dst.stat().st_size,
    )


def cut_file(src: Path, dst: Path, fraction: float = CUT_FRACTION, odd_bytes: int = CUT_ODD_BYTES) -> int:
    """Copy the first ``fraction`` of ``src`` (plus ``odd_bytes``) to ``dst``, as a killed recorder leaves it; returns the byte count."""
    n = int(src.stat().st_size * fraction) + odd_bytes
    dst.write_bytes(src.read_bytes()[:n])
    return n


def _camera_dict(camera: Camera) -> dict:
    i, d = camera.intrinsics, camera.distortion
    return {
        "width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy,
        "distortion_k1_k2_p1_p2_k3": [float(v) for v in d.as_array()],
        "camera_position_enu_m": [float(v) for v in camera.pose.position_world],
        "enu_origin": list(camera.enu_origin) if camera.enu_origin is not None else None,
    }


def main(argv: list[str] | None = None) -> int:
    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.demo import run_demo

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=HERE, help="where the replays go (default: this folder)")
    parser.add_argument("--work", type=Path, default=None, help="where the full recordings go (default: a temporary folder)")
    parser.add_argument("--keep-recordings", action="store_true", help="keep the full recordings in --work")
    parser.add_argument("--reuse", action="store_true", help="shrink recordings already in --work instead of flying again")
    parser.add_argument("--speedup", type=float, default=3.0, help="simulator speed-up (default 3, as make demo)")
    parser.add_argument("--fps", type=float, default=15.0, help="camera frame rate (default 15, as make demo)")
    parser.add_argument("--hold-frames", type=int, default=3, help="frames kept per hover window (default 3)")
    parser.add_argument("--transitions", type=int, default=4, help="moves between holds kept (default 4)")
    parser.add_argument("--transition-step", type=int, default=2, help="keep every N-th frame of a move (default 2)")
    parser.add_argument("--jpeg-quality", type=int, default=75)
    args = parser.parse_args(argv)

    work = args.work or Path(tempfile.mkdtemp(prefix="dronecal-replays-"))
    args.out.mkdir(parents=True, exist_ok=True)
    manifest: dict[str, dict] = {}
    for spec in RECORDED:
        rec = work / spec.name
        if not (args.reuse and (rec / "run.mcap").exists()):
            print(f"recording {spec.name} (latency {spec.latency_s:g} s) into {rec}", flush=True)
            result = run_demo(rec, speedup=args.speedup, trials=50, fps=args.fps, echo=lambda s: print("  " + s, flush=True),
                              latency_s=spec.latency_s)
            print(f"  full-resolution calibration: focal {result.focal_error_pct:.2f} %, principal point "
                  f"{result.principal_point_error_px:.1f} px, position {result.position_error_cm:.1f} cm", flush=True)
        truth = half_resolution(read_camera(rec / "truth.yaml"))
        mcap = args.out / f"{spec.name}.mcap"
        report = shrink_run(rec / "run.mcap", mcap, spec.latency_s, args.hold_frames, args.transitions, args.transition_step,
                            args.jpeg_quality)
        write_camera(args.out / f"{spec.name}.truth.yaml", truth,
                     comment=f"truth of replays/{spec.name}.mcap: the simulator's camera at half resolution")
        print(f"  {mcap.name}: {report.frames_kept} of {report.frames_in} frames, {report.windows} hover windows, "
              f"{report.bytes_out / 1e6:.2f} MB", flush=True)
        manifest[spec.name] = {
            "file": mcap.name, "truth": f"{spec.name}.truth.yaml", "what": spec.what,
            "camera_latency_s": spec.latency_s, "speedup": args.speedup, "fps": args.fps,
            "frames_recorded": report.frames_in, "frames_kept": report.frames_kept, "hover_windows": report.windows,
            "fixes": report.fixes, "events": report.events, "attitudes": report.attitudes, "mavlink": report.mavlink,
            "bytes": report.bytes_out, "recorded_bytes": (rec / "run.mcap").stat().st_size, "truth_camera": _camera_dict(truth),
        }

    nominal = manifest["nominal"]
    cut = args.out / "cutoff.mcap"
    n = cut_file(args.out / nominal["file"], cut)
    shutil.copyfile(args.out / nominal["truth"], args.out / "cutoff.truth.yaml")
    manifest["cutoff"] = {
        "file": cut.name, "truth": "cutoff.truth.yaml",
        "what": f"nominal.mcap cut off at byte {n} of {nominal['bytes']} ({CUT_FRACTION:.0%} + {CUT_ODD_BYTES}), "
                "as a recorder killed mid-flight leaves it: no summary, the last chunk incomplete",
        "camera_latency_s": 0.0, "cut_from": nominal["file"], "cut_at_byte": n, "bytes": n,
        "truth_camera": nominal["truth_camera"],
    }
    (args.out / "replays.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"cutoff.mcap: {n} bytes; wrote {args.out / 'replays.json'}")
    if args.work is None and not args.keep_recordings:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
