"""The ``dronecal-field`` command line: parse, call the library, print.

Each sub-command lives in ``dronecal_field/commands/<name>.py`` and exposes
``register(subparsers)``; heavy imports (cv2, scipy) happen inside the
command's run function so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import sys

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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


if __name__ == "__main__":
    raise SystemExit(main())
