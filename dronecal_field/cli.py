"""The ``dronecal-field`` command line: parse, call the library, print.

Each sub-command lives in ``dronecal_field/commands/<name>.py`` and exposes
``register(subparsers)``; heavy imports (cv2, scipy) happen inside the
command's run function so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import math
import os
import sys
from pathlib import Path
from typing import NoReturn

# Order is the order in --help.
COMMANDS: tuple[str, ...] = (
    "demo",
    "plan",
    "fly",
    "calibrate",
    "import_run",
    "uncertainty",
    "survey",
    "sim",
)


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a bad flag in one line (the usage block hides it on a small screen).

    Sub-parsers inherit the class, so every command answers the same way.
    """

    def __init__(self, *args, **kwargs) -> None:
        # Command docstrings double as --help: drop their RST literal quotes (``x``), which a terminal shows as is.
        for key in ("description", "epilog"):
            if kwargs.get(key):
                kwargs[key] = kwargs[key].replace("``", "")
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="dronecal-field",
        description="Calibrate fixed cameras by flying an RTK drone with a marker through their view.",
    )
    parser.add_argument("--version", action="version", version=_version())
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"dronecal_field.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"dronecal_field.commands.{name}":
                continue  # command not built yet
            raise
        module.register(subparsers)
    return parser


def _version() -> str:
    from dronecal_field import __version__

    return f"dronecal-field {__version__}"


_STOP = {"count": 0, "active": False}  # stop signals seen by this process's handler (main thread)


class _NeverLost:
    """A stop exception that a library swallows is raised again.

    Some libraries catch everything in places (pymavlink's and ssl's imports run under a bare
    ``except``): a stop raised there would be dropped and the command would run on. When such an
    exception is dropped outside this package (the frame that caught it, the head of its traceback,
    is not ours), the signal is sent again, and raised again at the next step.
    """

    signum = 0

    def __del__(self) -> None:
        try:
            tb = self.__traceback__
            if not _STOP["active"] or tb is None:
                return
            if str(tb.tb_frame.f_globals.get("__name__", "")).startswith("dronecal_field"):
                return  # ours caught it: handled (or passed on) on purpose
            import threading

            _STOP["count"] = 0
            # Sent from another thread, so the handler raises in the main thread's next step, not in here.
            threading.Timer(0.01, os.kill, (os.getpid(), self.signum)).start()
        except Exception:  # noqa: BLE001 - never raise from a finaliser
            pass


class Interrupted(_NeverLost, KeyboardInterrupt):
    """Ctrl-C (SIGINT), as KeyboardInterrupt."""

    signum = 2


class Stopped(_NeverLost, KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread like Ctrl-C so every command's clean-up runs."""

    def __init__(self, signum: int) -> None:
        import signal

        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _install_stop_signals() -> None:
    """SIGINT, SIGTERM and SIGHUP stop a command cleanly: the first raises (Ctrl-C's KeyboardInterrupt,
    or :class:`Stopped`), so ``finally`` blocks finalise a recording and remove temporary outputs; a
    second one during that clean-up is said and ignored, a third stops at once."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    _STOP["active"] = True

    def handler(signum, _frame):
        _STOP["count"] += 1
        if _STOP["count"] == 1:
            if _DEFERRED["depth"] > 0:
                _DEFERRED["pending"] = signum  # raised when the deferred block ends
                return
            _raise_stop(signum)
        if _STOP["count"] == 2:
            print(f"dronecal-field: {signal.Signals(signum).name} again: still finishing the files; a third signal stops at once",
                  file=sys.stderr, flush=True)
            return
        os._exit(128 + signum)

    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None:
            continue
        if name == "SIGINT" and signal.getsignal(sig) is not signal.default_int_handler:
            continue  # started with SIGINT ignored (nohup, a background job): keep it so
        signal.signal(sig, handler)


_DEFERRED = {"depth": 0, "pending": None}  # stop signals held back by stop_signals_deferred (main thread only)


@contextlib.contextmanager
def stop_signals_deferred():
    """Hold a stop (SIGINT/SIGTERM/SIGHUP) back for the block, and raise it right after the block.

    For steps that import or call libraries that swallow exceptions (pymavlink's and ssl's imports
    catch everything), and for steps that must not be cut in the middle (create a file, then note it).
    """
    _DEFERRED["depth"] += 1
    try:
        yield
    finally:
        _DEFERRED["depth"] -= 1
    pending = _DEFERRED["pending"]
    if pending is not None and _DEFERRED["depth"] == 0:
        _DEFERRED["pending"] = None
        _raise_stop(pending)


def _raise_stop(signum: int) -> None:
    import signal

    if signum == signal.SIGINT:
        raise Interrupted
    raise Stopped(signum)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if argv is None:  # a process of its own (not a test calling main in-process)
        _install_stop_signals()
        rc = _run_command(args)
        _STOP["active"] = False
        return leave_cleanly(rc)
    return _run_command(args)


def leave_cleanly(rc: int, grace_s: float = 2.0) -> int:
    """Exit code ``rc`` once no daemon thread still runs: a thread inside native code (OpenCV, FFmpeg, numba)
    when the interpreter finalises is unwound by force and aborts the process ("terminate called without an
    active exception", exit 134). Each gets ``grace_s`` in all to end; if one does not, the process leaves
    without finalising (every command has closed its files by now; stdout and stderr are flushed)."""
    import threading
    import time

    deadline = time.monotonic() + grace_s
    # Threads started outside Python (the Foxglove server's, FFmpeg's) show up as dummies: they cannot be joined
    # and the interpreter does not unwind them.
    ours = [t for t in threading.enumerate() if t.daemon and t is not threading.current_thread() and not isinstance(t, threading._DummyThread)]
    for thread in ours:
        thread.join(timeout=max(0.0, deadline - time.monotonic()))
    lingering = [t.name for t in ours if t.is_alive()]
    if lingering:
        if os.environ.get("DRONECAL_REPORT_THREADS"):
            print(f"dronecal-field: threads still running at exit: {', '.join(lingering)}", file=sys.stderr)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(rc)
    return rc


def _run_command(args) -> int:
    from dronecal_field.errors import DronecalError

    try:
        return int(args.func(args) or 0)
    except DronecalError as exc:
        print(f"dronecal-field {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, UnicodeDecodeError, MemoryError) as exc:
        # The environment, not the program: a path, a permission, a disk, a file that is not text.
        print(f"dronecal-field {args.command}: error: {environment_message(exc)}", file=sys.stderr)
        return 2
    except Stopped as exc:
        print(f"dronecal-field {args.command}: stopped by {exc}", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        print(f"dronecal-field {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0


def environment_message(exc: BaseException) -> str:
    """One line naming the file and the fix for an error of the machine rather than of the program."""
    if isinstance(exc, UnicodeDecodeError):
        return f"a file is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): give the text file the option asks for"
    if isinstance(exc, MemoryError):
        return "out of memory: the input is too large for this machine; give fewer points or frames"
    assert isinstance(exc, OSError)
    what = exc.strerror or type(exc).__name__
    if exc.filename is not None:
        target = f"{exc.filename}" + (f" -> {exc.filename2}" if exc.filename2 else "")
        return f"{target}: {what}: check the path exists, is the kind expected (file or folder) and is writable/readable by you"
    return f"{what}: check the paths, the network address and the free disk space"


COMPILE_NOTICE = "dronecal-field: compiling the numerical kernels once (first run after install: about 15-45 s on 2 cores; cached afterwards)"


def announce_first_compile(now: bool = False) -> None:
    """One line on stderr when the numerical kernels are about to be compiled (else the first run sits silent).

    Said just before the first solve that compiles (a command that fails on its input first says only why);
    ``now`` says it at once, for a command whose child processes will compile (the demo).
    """
    from dronecal_field.core.kernels import announce_compile_with, cache_is_cold

    def notice() -> None:
        print(COMPILE_NOTICE, file=sys.stderr, flush=True)

    if now:
        if cache_is_cold():
            notice()
    else:
        announce_compile_with(notice)


# --------------------------------------------------------------------------
# Flag checks shared by the commands: each raises InputError with one line
# naming the flag, the value and what to give instead. 0 is a value, never
# "unset": a flag left out is None.


def check_number(flag: str, value: float | None, low: float, high: float, *, low_open: bool = False, hint: str = "") -> None:
    """``value`` must be finite and within [low, high] (``(low, high]`` with ``low_open``); None passes."""
    from dronecal_field.errors import InputError

    if value is None:
        return
    bracket = "(" if low_open else "["
    ok = math.isfinite(value) and (value > low if low_open else value >= low) and value <= high
    if not ok:
        raise InputError(f"{flag} {value:g} is outside {bracket}{low:g}, {high:g}]" + (f": {hint}" if hint else ""))


def check_numbers(flag: str, text: str, n: int, *, low: float = -math.inf, high: float = math.inf, hint: str = "") -> tuple[float, ...]:
    """``n`` finite comma-separated numbers within [low, high], e.g. a marker offset ``0.1,0,0.05``."""
    from dronecal_field.errors import InputError

    try:
        values = tuple(float(v) for v in str(text).split(","))
    except ValueError:
        values = ()
    if len(values) != n or not all(math.isfinite(v) and low <= v <= high for v in values):
        raise InputError(f"{flag} {text!r} is not {n} finite comma-separated numbers" + (f" within [{low:g}, {high:g}]" if math.isfinite(low) or math.isfinite(high) else "")
                         + (f": {hint}" if hint else ""))
    return values


def check_seed(flag: str, seed: int | None) -> None:
    """Seeds feed numpy, which takes 0 .. 2**32 - 1."""
    from dronecal_field.errors import InputError

    if seed is not None and not 0 <= seed < 2**32:
        raise InputError(f"{flag} {seed} is outside 0..4294967295: give a non-negative seed, e.g. 0")


def check_out_dir(flag: str, path: str | os.PathLike) -> None:
    """An output folder: a folder or a free name, in an existing folder this user can write in."""
    from dronecal_field.errors import InputError

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{flag} {p} is a file, not a folder: choose a folder name")
    _check_parent(flag, p)


def check_out_file(flag: str, path: str | os.PathLike, *, keep_existing: bool = False) -> None:
    """An output file: not a folder, in an existing writable folder; ``keep_existing`` refuses to replace one."""
    from dronecal_field.errors import InputError

    p = Path(path)
    if p.is_dir():
        raise InputError(f"{flag} {p} is a folder: give a file name in it, e.g. {p / 'out'}{p.suffix or ''}")
    if keep_existing and p.exists():
        raise InputError(f"{flag} {p} already exists; nothing was overwritten: choose a new name or move the old file away")
    _check_parent(flag, p)


def _check_parent(flag: str, p: Path) -> None:
    import tempfile

    from dronecal_field.errors import InputError

    parent = p.absolute().parent
    if not parent.is_dir():
        raise InputError(f"{flag} {p}: folder {parent} does not exist: create it first or choose another path")
    try:  # the only sure test of "writable" (permission bits lie for root and read-only mounts)
        with tempfile.TemporaryFile(dir=parent, prefix=".dronecal-probe-"):
            pass
    except OSError as exc:
        raise InputError(f"{flag} {p}: cannot write in {parent} ({exc.strerror or exc}): choose a folder you can write to") from None


def check_input_file(flag: str, path: str | os.PathLike | None) -> None:
    """An input file must exist and be a file (not a folder)."""
    from dronecal_field.errors import InputError

    if path is None:
        return
    p = Path(path)
    if not p.exists():
        raise InputError(f"{flag} {p} does not exist: check the path")
    if not p.is_file():  # a folder, or a FIFO (would wait for a writer for ever) or a device (/dev/zero never ends)
        raise InputError(f"{flag} {p} is not a regular file: give the file itself")


def check_marker(dictionary: str, marker_id: int | None, *, dict_flag: str = "--marker-dictionary", id_flag: str = "--marker-id") -> None:
    """An OpenCV ArUco dictionary name, and an id that the dictionary holds."""
    import cv2

    from dronecal_field.errors import InputError

    code = getattr(cv2.aruco, dictionary, None) if dictionary.startswith("DICT_") else None
    if not isinstance(code, int):
        raise InputError(f"{dict_flag} {dictionary!r} is not an OpenCV ArUco dictionary: use e.g. DICT_4X4_50")
    if marker_id is not None:
        n = cv2.aruco.getPredefinedDictionary(code).bytesList.shape[0]
        if not 0 <= marker_id < n:
            raise InputError(f"{id_flag} {marker_id} is not in {dictionary} (ids 0..{n - 1}): give the id printed on the marker")


def check_address(flag: str, url: str, schemes: tuple[str, ...]) -> None:
    """``scheme:HOST:PORT`` (or ``scheme://HOST:PORT/path``) with a known scheme and a port 0-65535."""
    from urllib.parse import urlsplit

    from dronecal_field.errors import InputError

    example = f"{schemes[0]}:127.0.0.1:14550" if "//" not in url else f"{schemes[0]}://127.0.0.1:8554/stream"
    scheme = url.split(":", 1)[0].lower() if ":" in url else ""
    if scheme not in schemes:
        raise InputError(f"{flag} {url!r} has no known scheme ({', '.join(schemes)}): write e.g. {example}")
    try:
        if "//" in url:
            parts = urlsplit(url)
            port = parts.port
            host = parts.hostname
        else:
            host, _, port_text = url.split(":", 1)[1].rpartition(":")
            port = int(port_text)
            if not host or "[" in host or "]" in host:
                raise ValueError("no host")
    except ValueError:
        raise InputError(f"{flag} {url!r} is not a valid address: write e.g. {example}") from None
    if port is not None and not 0 <= port <= 65535:
        raise InputError(f"{flag} {url!r}: port {port} is outside 0-65535: write e.g. {example}")
    if not host:
        raise InputError(f"{flag} {url!r} names no host: write e.g. {example}")


if __name__ == "__main__":
    raise SystemExit(main())
