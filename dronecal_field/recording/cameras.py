"""The cameras of one recording, from ``fly --video URL`` or ``fly --video NAME=URL`` (repeatable).

A bare ``--video URL`` is the single camera of a ``/camera/...`` run, as it
always was. ``--video NAME=URL`` (once or several times) makes a
several-camera run (contract "Several cameras in one run"): each camera on
``/cameras/<NAME>/image|video``. Pure: no sockets, no files.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from dronecal_field.errors import InputError
from dronecal_field.runfile.writer import CAMERA_NAME_PATTERN

_NOT_A_NAME = re.compile(r"[:/.?&\\\\]")  # a URL's or a path's characters: text before '=' holding one is no name
MAX_CAMERAS = 16


@dataclass(frozen=True)
class VideoSpec:
    """One ``--video``: the camera's name (None for a bare URL) and its stream."""

    name: str | None
    url: str

    @property
    def flag(self) -> str:
        """How messages name it: ``--video`` or ``--video north``."""
        return "--video" if self.name is None else f"--video {self.name}"


def parse_video_flags(values: list[str]) -> list[VideoSpec]:
    """The cameras of ``--video`` values; one-line InputError for a bad name, a repeat or a mix.

    Examples
    --------
    >>> parse_video_flags(["rtsp://cam/stream"])
    [VideoSpec(name=None, url='rtsp://cam/stream')]
    >>> [v.name for v in parse_video_flags(["north=rtsp://a/s", "south=http://b/s.mjpg"])]
    ['north', 'south']
    """
    specs = [_one(v) for v in values]
    if not specs:
        raise InputError("no --video given: give the camera's stream, e.g. --video rtsp://camera/stream")
    if len(specs) > MAX_CAMERAS:
        raise InputError(f"--video given {len(specs)} times: record at most {MAX_CAMERAS} cameras in one run")
    if len(specs) > 1 and any(s.name is None for s in specs):
        bare = next(s.url for s in specs if s.name is None)
        raise InputError(f"--video {bare!r} has no name but there are {len(specs)} cameras: "
                         "name each one, e.g. --video north=rtsp://... --video south=http://.../stream.mjpg")
    names = [s.name for s in specs if s.name is not None]
    for name in names:
        if names.count(name) > 1:
            raise InputError(f"--video {name}=... is given twice: give each camera its own name")
    urls = [s.url for s in specs]
    for url in urls:
        if urls.count(url) > 1:
            raise InputError(f"--video stream {url!r} is given twice: each camera needs its own stream")
    return specs


def _one(value: str) -> VideoSpec:
    name, sep, url = value.partition("=")
    if not sep or _NOT_A_NAME.search(name) or not name:
        return VideoSpec(None, value)  # a URL or a path (its '=' is in a query)
    if not re.fullmatch(CAMERA_NAME_PATTERN, name):
        raise InputError(f"--video {value!r}: camera name {name!r} is not [a-z0-9][a-z0-9_-]{{0,31}} "
                         "(lower-case letters, digits, '_' or '-', at most 32, starting with a letter or digit); rename it, e.g. --video north=URL")
    if not url:
        raise InputError(f"--video {value!r} names camera {name!r} but gives no stream: write --video {name}=rtsp://... or {name}=http://.../stream.mjpg")
    return VideoSpec(name, url)


def camera_plan(plan_json: dict | None, name: str) -> dict | None:
    """plan.json's entry for camera ``name``: ``cameras`` as a mapping by name or a list of objects with ``name``."""
    cams = (plan_json or {}).get("cameras") if isinstance(plan_json, dict) else None
    sub = None
    if isinstance(cams, dict):
        sub = cams.get(name)
    elif isinstance(cams, list):
        sub = next((c for c in cams if isinstance(c, dict) and c.get("name") == name), None)
    return sub if isinstance(sub, dict) else None
