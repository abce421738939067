"""Output folders written as one set: into a temporary sibling that replaces the folder at the end.

An interruption (Ctrl-C, a full disk) leaves the previous folder as it was,
never a new camera.yaml beside an old report; the files in the old folder that
the command did not write (the user's notes, photos) move into the new one.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def staged_folder(out: Path) -> Iterator[Path]:
    """A new empty folder beside ``out`` to write into; removed if the block fails (``out`` untouched)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_folder(new: Path, out: Path, ours: Callable[[str], bool]) -> None:
    """Put the folder ``new`` in place of ``out``; entries of the old ``out`` for which ``ours(name)`` is False move across.

    Entries ``ours`` claims (the command's own outputs of an earlier run, stale
    ones included) are dropped; a name the new folder already has is not moved.
    """
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(new, 0o777 & ~umask)  # mkdtemp makes it private; an output folder is an ordinary one
    if not out.exists():
        os.rename(new, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    os.rename(out, old / out.name)
    os.rename(new, out)
    for entry in (old / out.name).iterdir():
        if not ours(entry.name) and not (out / entry.name).exists():
            os.rename(entry, out / entry.name)  # the user's file: same file system, a rename
    shutil.rmtree(old, ignore_errors=True)
