"""ArduPilot's own ArduCopter 4.7 SITL for the tests: start it, reach it, stop it.

The binary is a tool outside the project (``../shared/sitl/arducopter-4.7/``,
README there): tests that need it skip with the reason when it is absent.
Each :class:`ArduCopterSitl` runs in a fresh temporary working directory
(SITL writes ``eeprom.bin`` and ``logs/`` there), with ``-w`` (wiped
parameters), ``--defaults copter.parm,<ours>.parm``, explicit
``--serial0``/``--serial1 udpclient:127.0.0.1:PORT`` links and a free ``-I``
instance. Where ``unshare -n`` works (root) it runs in a private network
namespace whose only interface is loopback, so nothing it binds on 0.0.0.0 is
reachable from outside; the clients then join that namespace too: processes
through ``nsenter --net=...`` (:meth:`ArduCopterSitl.argv`), sockets of this
process through :meth:`ArduCopterSitl.netns` (``setns(2)`` on the calling
thread while the socket is created; a socket stays in the namespace it was
made in). Where it does not, it runs on plain loopback with free ports.

Example
-------
>>> with ArduCopterSitl.start(HOME, speedup=10) as sitl:      # doctest: +SKIP
...     with sitl.netns():
...         link = open_link(sitl.gcs_url)
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from typing import Self
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
def _sitl_dir() -> Path:
    """``$DRONECAL_ARDUCOPTER_SITL_DIR``, else ``../shared/sitl/arducopter-4.7`` beside the clone, else /work/shared's."""
    if os.environ.get("DRONECAL_ARDUCOPTER_SITL_DIR"):
        return Path(os.environ["DRONECAL_ARDUCOPTER_SITL_DIR"])
    for shared in (REPO.parent / "shared", Path("/work/shared")):
        if (shared / "sitl" / "arducopter-4.7" / "arducopter").is_file():
            return shared / "sitl" / "arducopter-4.7"
    return REPO.parent / "shared" / "sitl" / "arducopter-4.7"


SITL_DIR = _sitl_dir()
BINARY = SITL_DIR / "arducopter"
COPTER_PARM = SITL_DIR / "copter.parm"
CLONE_NEWNET = 0x40000000


def skip_reason() -> str | None:
    """Why the SITL tests cannot run here, or ``None`` when they can."""
    if not BINARY.is_file() or not os.access(BINARY, os.X_OK):
        return f"ArduCopter 4.7 SITL binary not found at {BINARY} (see ../shared/sitl/README.md)"
    if not COPTER_PARM.is_file():
        return f"copter.parm missing beside the SITL binary ({COPTER_PARM})"
    return None


needs_sitl = pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")


def _free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _instance_is_free(instance: int) -> bool:
    """SITL's default TCP serial listeners (5760 + 10 N ..) and its sim ports are free on loopback."""
    base = 5760 + 10 * instance
    for port in [*range(base, base + 8), 5501 + 10 * instance, 5502 + 10 * instance]:
        for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
            with socket.socket(socket.AF_INET, kind) as s:
                try:
                    s.bind(("0.0.0.0", port))
                except OSError:
                    return False
    return True


def _free_instance() -> int:
    for instance in range(11, 60):
        if _instance_is_free(instance):
            return instance
    raise RuntimeError("no free SITL instance (-I 11..59): every port range is in use")


def _unshare_works() -> bool:
    if os.environ.get("DRONECAL_SITL_NO_NETNS"):  # to test the plain-loopback fallback
        return False
    if shutil.which("unshare") is None or shutil.which("nsenter") is None or shutil.which("ip") is None:
        return False
    try:
        return subprocess.run(["unshare", "-n", "ip", "link", "set", "lo", "up"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


_libc = ctypes.CDLL(None, use_errno=True)


def _setns(fd: int) -> None:
    if _libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"setns: {os.strerror(err)}")


class SitlProcess:
    """What every firmware SITL here shares: reaching its loopback, stopping it. Needs ``proc``, ``private_net``, ``_tmp``."""

    proc: subprocess.Popen
    private_net: bool
    _tmp: tempfile.TemporaryDirectory | None

    def argv(self, argv: Sequence[str]) -> list[str]:
        """``argv`` run where it reaches SITL's loopback (inside its namespace when it has one)."""
        if not self.private_net:
            return list(argv)
        return ["nsenter", f"--net=/proc/{self.proc.pid}/ns/net", "--", *argv]

    @contextlib.contextmanager
    def netns(self) -> Iterator[None]:
        """Sockets this thread creates inside the block live in SITL's namespace (no-op without one)."""
        if not self.private_net:
            yield
            return
        own = os.open(f"/proc/self/task/{threading.get_native_id()}/ns/net", os.O_RDONLY)
        target = os.open(f"/proc/{self.proc.pid}/ns/net", os.O_RDONLY)
        try:
            _setns(target)
            try:
                yield
            finally:
                _setns(own)
        finally:
            os.close(own)
            os.close(target)

    def stop(self) -> None:
        """SIGTERM the firmware (this pid only), SIGKILL if it lingers; remove its working directory."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@dataclass
class ArduCopterSitl(SitlProcess):
    """A running ArduCopter SITL (one process), its two links and its working directory.

    Attributes
    ----------
    proc : subprocess.Popen
        The SITL (``unshare`` execs into it, so its pid is the firmware's).
    workdir : Path
        Its fresh working directory (eeprom.bin, logs/, sitl.log).
    gcs_url, second_url : str
        ``udpin:127.0.0.1:PORT`` for SERIAL0 (the ground station's link) and
        SERIAL1 (a second link, e.g. the camera simulator); SITL sends to them.
    speedup : float
        ``--speedup``: simulated seconds per wall second, at most.
    private_net : bool
        True when it runs in its own network namespace (reach it with
        :meth:`netns` / :meth:`argv`).
    """

    proc: subprocess.Popen
    workdir: Path
    gcs_url: str
    second_url: str
    speedup: float
    private_net: bool
    instance: int
    _tmp: tempfile.TemporaryDirectory | None = field(default=None, repr=False)

    @classmethod
    def start(
        cls,
        home: tuple[float, float, float],
        *,
        heading_deg: float = 90.0,
        speedup: float = 10.0,
        params: Mapping[str, float] | None = None,
        model: str = "+",
    ) -> ArduCopterSitl:
        """Start SITL at ``home`` (lat deg, lon deg, metres AMSL) with ``params`` in a defaults file after copter.parm.

        Raises
        ------
        RuntimeError
            The binary is absent (tests skip before this) or exits at once.
        """
        reason = skip_reason()
        if reason is not None:
            raise RuntimeError(reason)
        tmp = tempfile.TemporaryDirectory(prefix="arducopter-sitl-")
        workdir = Path(tmp.name)
        parm = workdir / "tests.parm"
        parm.write_text("".join(f"{name} {value}\n" for name, value in (params or {}).items()))
        private = _unshare_works()
        instance = 0 if private else _free_instance()
        port0, port1 = (14581, 14582) if private else (_free_port(), _free_port())
        lat, lon, alt = home
        sitl_argv = [
            str(BINARY), "--model", model, "--speedup", f"{speedup:g}", "--defaults", f"{COPTER_PARM},{parm}",
            f"-I{instance}", "--home", f"{lat!r},{lon!r},{alt!r},{heading_deg:g}", "-w",
            "--serial0", f"udpclient:127.0.0.1:{port0}", "--serial1", f"udpclient:127.0.0.1:{port1}",
        ]  # fmt: skip
        if private:
            # unshare execs bash in the new namespace, bash execs SITL: one pid throughout
            argv = ["unshare", "-n", "bash", "-c", 'ip link set lo up && exec "$0" "$@"', *sitl_argv]
        else:
            argv = sitl_argv
        log = (workdir / "sitl.log").open("w")
        proc = subprocess.Popen(argv, cwd=workdir, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        log.close()
        sitl = cls(proc, workdir, f"udpin:127.0.0.1:{port0}", f"udpin:127.0.0.1:{port1}", speedup, private, instance, tmp)
        if private:
            sitl._wait_for_namespace()
        return sitl

    def _wait_for_namespace(self, timeout_s: float = 10.0) -> None:
        """Until the SITL's network namespace differs from ours (the exec into ``unshare -n`` is done)."""
        import time

        mine = os.stat("/proc/self/ns/net").st_ino
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"SITL exited at start (code {self.proc.returncode}): {self.log_tail()}")
            try:
                if os.stat(f"/proc/{self.proc.pid}/ns/net").st_ino != mine and os.readlink(f"/proc/{self.proc.pid}/exe") == str(BINARY.resolve()):
                    return
            except OSError:
                pass
            time.sleep(0.02)
        raise RuntimeError(f"SITL did not start in its namespace within {timeout_s:.0f} s: {self.log_tail()}")

    def log_tail(self, lines: int = 5) -> str:
        """The last lines SITL printed (for failure messages)."""
        try:
            return " | ".join((self.workdir / "sitl.log").read_text(errors="replace").strip().splitlines()[-lines:])
        except OSError:
            return "(no log)"


def wait_for_http(sitl: SitlProcess, port: int, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Until ``proc`` (a sim camera) serves on ``port`` inside the SITL's namespace."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, "sim camera exited early"
        try:
            with sitl.netns():
                s = socket.create_connection(("127.0.0.1", port), timeout=0.5)
            s.close()
            return
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"sim camera did not serve on {port} within {timeout_s:.0f} s")
