"""PX4 1.16 SITL (SIH physics) for the tests: start it, reach it, stop it.

The firmware is a tool outside the project (``../shared/sitl/px4-1.16/``,
README there): tests that need it skip with the reason when it is absent or
when private namespaces are not available. Each :class:`Px4Sitl` runs

* in a fresh working directory (``-w``: parameters and the stored mission
  live there, so it is a clean vehicle), outside ``/tmp``;
* with its own ``bin/``: the shared tree stores the ``px4-<module>`` links as
  small text files, so links to the ``px4`` binary are made there;
* in a private network namespace with only loopback (``unshare -n``: PX4
  binds 0.0.0.0) and a private mount namespace with a tmpfs on ``/tmp``
  (``unshare -m``: its ``/tmp/px4_lock-0`` and ``/tmp/px4-sock-0``), so
  several can run at once, each as instance 0.

Clients join the network namespace like tests/sitl.py's: processes through
:meth:`Px4Sitl.argv` (``nsenter --net``), sockets of this process through
:meth:`Px4Sitl.netns`. The GCS link sends to 127.0.0.1:14550
(:attr:`gcs_url`), the onboard link to 127.0.0.1:14540 (:attr:`second_url`).
PX4 runs in real time only.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from sitl import REPO, SitlProcess, _unshare_works


def _px4_dir() -> Path:
    """``$DRONECAL_PX4_SITL_DIR``, else ``../shared/sitl/px4-1.16`` beside the clone, else /work/shared's."""
    if os.environ.get("DRONECAL_PX4_SITL_DIR"):
        return Path(os.environ["DRONECAL_PX4_SITL_DIR"])
    for shared in (REPO.parent / "shared", Path("/work/shared")):
        if (shared / "sitl" / "px4-1.16" / "bin" / "px4").is_file():
            return shared / "sitl" / "px4-1.16"
    return REPO.parent / "shared" / "sitl" / "px4-1.16"


PX4_DIR = _px4_dir()
BINARY = PX4_DIR / "bin" / "px4"
ETC = PX4_DIR / "etc"


def _mount_ns_works() -> bool:
    try:
        return subprocess.run(["unshare", "-m", "-n", "bash", "-c", "mount -t tmpfs tmpfs /tmp"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def skip_reason() -> str | None:
    """Why the PX4 SITL tests cannot run here, or ``None`` when they can."""
    if not BINARY.is_file() or not os.access(BINARY, os.X_OK):
        return f"PX4 1.16 SITL binary not found at {BINARY} (see ../shared/sitl/README.md)"
    if not (ETC / "init.d-posix" / "rcS").is_file():
        return f"PX4's start-up tree missing beside the binary ({ETC})"
    if not _unshare_works() or not _mount_ns_works():
        return "PX4 SITL binds 0.0.0.0 and locks /tmp/px4_lock-0: these tests run it in private network and mount namespaces (unshare -n -m, root)"
    return None


needs_px4 = pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")


def _private_bin(workdir: Path) -> Path:
    """``workdir/bin``: ``px4`` and its ``px4-<module>`` links (the shared tree keeps them as text files)."""
    bindir = workdir / "bin"
    bindir.mkdir()
    (bindir / "px4").symlink_to(BINARY)
    for path in (PX4_DIR / "bin").iterdir():
        if path.name == "px4-alias.sh":
            shutil.copy(path, bindir / path.name)
        elif path.name.startswith("px4-"):
            (bindir / path.name).symlink_to("px4")
    return bindir / "px4"


@dataclass
class Px4Sitl(SitlProcess):
    """A running PX4 SITL with SIH, its links and its working directory.

    Attributes
    ----------
    proc : subprocess.Popen
        The firmware (``unshare`` execs bash, bash execs px4: one pid).
    workdir : Path
        Its fresh working directory (parameters, dataman, logs, px4.log).
    gcs_url, second_url : str
        ``udpin:127.0.0.1:14550`` (the GCS link) and ``udpin:127.0.0.1:14540``
        (the onboard link, e.g. the camera simulator), inside its namespace.
    """

    proc: subprocess.Popen
    workdir: Path
    gcs_url: str = "udpin:127.0.0.1:14550"
    second_url: str = "udpin:127.0.0.1:14540"
    private_net: bool = True
    _tmp: tempfile.TemporaryDirectory | None = field(default=None, repr=False)

    @classmethod
    def start(cls, home: tuple[float, float, float], *, params: Mapping[str, float] | None = None) -> Px4Sitl:
        """Start PX4 SIH quad at ``home`` (lat deg, lon deg, metres AMSL); ``params`` as ``PX4_PARAM_<NAME>``.

        Raises
        ------
        RuntimeError
            Not runnable here (tests skip before this) or it exits at once.
        """
        reason = skip_reason()
        if reason is not None:
            raise RuntimeError(reason)
        tmp = tempfile.TemporaryDirectory(prefix="px4-sitl-", dir="/var/tmp" if Path("/var/tmp").is_dir() else None)
        workdir = Path(tmp.name)
        px4 = _private_bin(workdir)
        lat, lon, alt = home
        env = {
            **os.environ,
            "PX4_SYS_AUTOSTART": "10040", "PX4_SIMULATOR": "sihsim", "PX4_SIM_MODEL": "sihsim_quadx",
            "PX4_HOME_LAT": repr(lat), "PX4_HOME_LON": repr(lon), "PX4_HOME_ALT": repr(alt),
            **{f"PX4_PARAM_{name}": str(value) for name, value in (params or {}).items()},
        }  # fmt: skip
        argv = ["unshare", "-n", "-m", "bash", "-c", 'ip link set lo up && mount -t tmpfs tmpfs /tmp && exec "$0" "$@"',
                str(px4), "-d", "-w", str(workdir), str(ETC)]  # fmt: skip
        log = (workdir / "px4.log").open("w")
        proc = subprocess.Popen(argv, cwd=workdir, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        log.close()
        sitl = cls(proc, workdir, _tmp=tmp)
        sitl._wait_for_namespace()
        return sitl

    def _wait_for_namespace(self, timeout_s: float = 10.0) -> None:
        mine = os.stat("/proc/self/ns/net").st_ino
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"PX4 exited at start (code {self.proc.returncode}): {self.log_tail()}")
            try:
                if os.stat(f"/proc/{self.proc.pid}/ns/net").st_ino != mine and os.readlink(f"/proc/{self.proc.pid}/exe") == str(BINARY.resolve()):
                    return
            except OSError:
                pass
            time.sleep(0.02)
        raise RuntimeError(f"PX4 did not start in its namespace within {timeout_s:.0f} s: {self.log_tail()}")

    def log_tail(self, lines: int = 8) -> str:
        """The last lines PX4 printed (for failure messages)."""
        try:
            return " | ".join((self.workdir / "px4.log").read_text(errors="replace").strip().splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def warnings(self) -> str:
        """PX4's WARN and ERROR lines (mission feasibility, pre-arm), for failure messages."""
        try:
            text = (self.workdir / "px4.log").read_text(errors="replace")
        except OSError:
            return "(no log)"
        return " | ".join(line for line in text.splitlines() if "WARN" in line or "ERROR" in line)[-3000:]

    def argv(self, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside PX4's network namespace (the host's /tmp and files stay visible)."""
        return ["nsenter", f"--net=/proc/{self.proc.pid}/ns/net", "--", *argv]


# The CI flight's holds for the demo camera (tests/test_px4_sim_flight.py's truth: 1280x720, f 1000 px, 4 m mast, tilt 25 deg):
# (u px, v px, range m) the marker is seen at. PX4 SITL's GNSS is white noise of ~0.2 m / 0.5 m per fix, so a hold's point is
# as good as the number of fixes averaged over its range: few long holds, far where the image allows it. The camera looks down
# 25 deg, so only the upper rows can be far (the middle row at 10 m would be under the ground): bottom row near (4.4-4.5 m,
# 1.4-1.6 m up), the middle row's ends at 7.5 m, the top row at 12 m. They stay ~150 px inside the image: PX4 holds the EKF's
# height, which wanders +-0.6 m from the truth (~100 px at 4.5 m), and the distortion 8 points cannot fit stays under ~15 px.
SPREAD_HOLDS: tuple[tuple[float, float, float], ...] = (
    (1000, 540, 4.5), (640, 560, 4.4), (280, 540, 4.5),  # bottom row, right to left
    (170, 340, 7.5), (220, 140, 12.0), (640, 120, 12.0), (1060, 140, 12.0), (1110, 340, 7.5),  # up the left, across the top, down
)


def spread_mission(out_path: Path, source: Path, truth_path: Path, *, holds: Sequence[tuple[float, float, float]] = SPREAD_HOLDS,
                   hold_s: float = 8.0, speed_m_s: float = 2.0, acceptance_m: float = 0.3) -> Path:
    """``source``'s take-off, speed, camera ROI and landing around holds where ``truth_path``'s camera sees the marker at ``holds``.

    Each (u, v, range) becomes a NAV_WAYPOINT held ``hold_s`` at the point on that pixel's ray (no distortion: the point lands
    within a few tens of pixels of it), the speed item is set to ``speed_m_s``; the rest of ``source`` is kept (its first
    hold item is the template). ``acceptance_m`` is each hold's acceptance radius (param 2): PX4 starts the hold's
    timer when the vehicle comes this close (0: its NAV_ACC_RAD, 2 m, so the hold ran out while still arriving).
    Written as a QGC .plan at ``out_path``.
    """
    from dataclasses import replace

    import numpy as np

    from dronecal_field.camerafile import read_camera
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic
    from dronecal_field.mavlink import missionfile as mf

    cam = read_camera(truth_path)
    origin = EnuOrigin(*cam.enu_origin)
    rot = cam.pose.R_cam_from_world
    centre = -rot.T @ cam.pose.t_cam_from_world
    fx, fy, cx, cy = cam.intrinsics.fx, cam.intrinsics.fy, cam.intrinsics.cx, cam.intrinsics.cy
    mission = mf.read_mission(source)
    first_hold = next(i for i, it in enumerate(mission.items) if it.command == mf.CMD_NAV_WAYPOINT and it.hold_s > 0)
    last_hold = max(i for i, it in enumerate(mission.items) if it.command == mf.CMD_NAV_WAYPOINT and it.hold_s > 0)
    template = mission.items[first_hold]
    new = []
    for u, v, rng in holds:
        ray = rot.T @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        at = centre + rng * ray / np.linalg.norm(ray)
        lat, lon, _h = enu_to_geodetic(at, origin)[0]
        yaw = math.degrees(math.atan2(centre[0] - at[0], centre[1] - at[1])) % 360.0  # facing the camera, as `plan` writes it
        new.append(replace(template, p1=hold_s, p2=acceptance_m, p4=round(yaw, 2), x=int(round(lat * 1e7)), y=int(round(lon * 1e7)),
                           z=round(float(at[2]), 2)))
    head = [replace(it, p2=speed_m_s) if it.command == mf.CMD_DO_CHANGE_SPEED else it for it in mission.items[:first_hold]]
    items = [*head, *new, *mission.items[last_hold + 1:]]
    items = [replace(it, seq=i) for i, it in enumerate(items)]
    out_path.write_text(mf.to_qgc_plan(replace(mission, items=tuple(items))))
    return out_path
