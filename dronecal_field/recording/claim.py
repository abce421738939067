"""A recording belongs to one process from its first byte: the run file and its .tlog are claimed at start.

``fly`` checks "never overwrite a flight" when it starts, but records minutes
later, after connecting, pre-flight and the upload. A second ``fly --out``
with the same name started in between passed the same check, and the later
of the two opened the file over the other's recording. :func:`claim_outputs`
creates both files exclusively (``O_CREAT | O_EXCL``) before anything is
connected, so the second process is refused in one line; the recorder then
writes into the files it owns. A run that stops before recording (pre-flight
failed, upload refused, Ctrl-C) gives the still-empty claims back.
"""

from __future__ import annotations

import os
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from dronecal_field.errors import InputError


def _same_file(a: Path, b: Path) -> bool:
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.abspath(a) == os.path.abspath(b)


@dataclass
class OutputClaim:
    """Output files created empty by this process; :meth:`release` removes those still empty."""

    paths: list[Path] = field(default_factory=list)
    _created: list[tuple[Path, int, int]] = field(default_factory=list)  # (path, st_dev, st_ino)

    def release(self) -> None:
        """Remove the claimed files that are still empty and still ours (nothing was recorded into them)."""
        for path, dev, ino in self._created:
            try:
                st = path.stat()
                if (st.st_dev, st.st_ino) == (dev, ino) and st.st_size == 0:
                    path.unlink()
            except OSError:
                pass
        self._created.clear()

    def keep(self) -> None:
        """The recording started: the files stay whatever happens."""
        self._created.clear()


def check_outputs(flag: str, outputs: list[Path], inputs: dict[str, Path | None]) -> None:
    """Refuse outputs that are the same file as each other or as an input, or in a folder that cannot be written.

    Parameters
    ----------
    flag : the option naming the first output, e.g. ``--out``.
    outputs : the files the command will write (the run, then the .tlog beside it).
    inputs : option name -> input file, compared by identity (``os.path.samefile``) and by path.
    """
    first = outputs[0]
    for other in outputs[1:]:
        if _same_file(first, other):
            raise InputError(f"{flag} {first}: the run and its .tlog would be the same file; name the run RUN.mcap, e.g. {flag} {first.with_suffix('.mcap')}")
    for out in outputs:
        for name, path in inputs.items():
            if path is not None and _same_file(out, Path(path)):
                raise InputError(f"{flag} {first}: {out.name} is also the input {name} {path}; give the run a new name, e.g. {flag} {Path(path).with_name('run.mcap')}")
    for out in outputs:
        if out.is_dir():
            raise InputError(f"{flag} {first}: {out} is a folder: give the run file's name, e.g. {flag} {out / 'run.mcap'}")
        if out.exists() and not stat.S_ISREG(out.stat().st_mode):
            raise InputError(f"{flag} {first}: {out} is not a regular file (a device or a pipe): give a file name")
    parent = first.absolute().parent
    if not parent.is_dir():
        raise InputError(f"{flag} {first}: directory {parent} does not exist; create it first")
    try:  # the only sure test of "writable" (permission bits lie for root and read-only mounts)
        with tempfile.TemporaryFile(dir=parent, prefix=".dronecal-probe-"):
            pass
    except OSError as exc:
        raise InputError(f"{flag} {first}: cannot write in {parent} ({exc.strerror or exc}): choose a folder you can write to") from None


# A recording takes about 1 MB/s at 10 fps of 1080p JPEG (more at 4K): below this, say so before flying.
LOW_DISK_BYTES = 2_000_000_000


def free_space_note(path: Path) -> str | None:
    """One line when the disk that will hold ``path`` has less than LOW_DISK_BYTES free, else None."""
    import shutil

    try:
        free = shutil.disk_usage(path.absolute().parent).free
    except OSError:
        return None
    if free >= LOW_DISK_BYTES:
        return None
    return (f"WARNING: only {free / 1e6:.0f} MB free for {path} (a flight records about 1 MB/s at 1080p, more at 4K); "
            "if the disk fills the recording stops there (finalised, said loudly): free space or choose another disk")


def claim_outputs(flag: str, outputs: list[Path], suggestion: Path | None = None, into: OutputClaim | None = None) -> OutputClaim:
    """Create every file of ``outputs`` empty and exclusively; InputError naming the one that exists.

    ``into``: an OutputClaim the caller already holds, filled as each file is created, so that a
    signal arriving at any moment finds every created file in it. On a refusal, the files this call
    created already are removed again.
    """
    claim = into if into is not None else OutputClaim()
    claim.paths = list(outputs)
    try:
        _create_each(flag, outputs, suggestion, claim)
    except BaseException:
        claim.release()
        raise
    return claim


def _create_each(flag: str, outputs: list[Path], suggestion: Path | None, claim: OutputClaim) -> None:
    for path in outputs:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            claim.release()
            empty = path.is_file() and path.stat().st_size == 0
            why = ("an empty file: another fly writing it now, or one stopped before it recorded"
                   if empty else "an earlier flight?")
            raise InputError(f"{flag} {outputs[0]}: {path.name} already exists ({why}); nothing was overwritten: "
                             f"choose a new name" + (f", e.g. {flag} {suggestion}" if suggestion else "")) from None
        except OSError as exc:
            claim.release()
            raise InputError(f"{flag} {outputs[0]}: cannot create {path} ({exc.strerror or exc}): choose a folder you can write to") from None
        try:
            st = os.fstat(fd)
            claim._created.append((path, st.st_dev, st.st_ino))
        finally:
            os.close(fd)
