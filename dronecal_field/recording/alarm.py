"""Video lost in flight: the console alarm and, only when asked (``fly --on-video-loss hold``), a held vehicle.

With several cameras each one is watched on its own: the pilot hears which
camera went quiet and how many still record; the others go on recording, so
by default nothing is commanded (the mission goes on for the cameras still
seeing it, and the lost one's waypoints are named for a re-fly). With
``hold``, the vehicle waits in GUIDED while any camera is lost and AUTO
resumes once every lost camera is back; a pilot who switches back to AUTO
during a loss flies on without that camera (it is not held again for the same
loss).
"""

from __future__ import annotations

from typing import Any


class VideoLossAlarm:
    """Frames stopping in flight is an alarm: a red line and a bell on the console, an alert in the live view and,
    with ``hold`` only, the vehicle held in GUIDED until frames return (then AUTO resumes the mission).

    Parameters
    ----------
    link : MavLink
        The vehicle (``set_mode``), used only with ``hold``.
    hold : bool
        ``--on-video-loss hold``.
    view : live.view.LiveView or None
        Told of each alert.
    """

    REPEAT_S = 15.0

    def __init__(self, link: Any, hold: bool = False, view: Any = None) -> None:
        self.link, self.hold, self.view = link, hold, view
        self.lost: dict[str | None, float] = {}  # camera name (None: the single camera) -> monotonic time it went quiet
        self._last_said: dict[str | None, float] = {}
        self.held = False
        self.losses = 0

    @property
    def lost_since(self) -> float | None:
        """When the earliest camera still lost went quiet (monotonic s), or None while every camera records."""
        return min(self.lost.values()) if self.lost else None

    def update(self, status: Any, now: float) -> list[tuple[str, bool]]:
        """(line, is an alarm) to print for this status (recorder.RecorderStatus) at monotonic ``now``."""
        cameras = [(c.name, c.video_ok) for c in status.cameras] if status.cameras else [(None, bool(status.video_ok))]
        lines: list[tuple[str, bool]] = []
        for name, ok in cameras:
            if not ok and name not in self.lost:
                lines.extend(self._lost(name, status, len(cameras), sum(1 for _n, o in cameras if o), now))
            elif not ok and now - self._last_said[name] >= self.REPEAT_S:
                self._last_said[name] = now
                which = "" if name is None else f" FROM CAMERA {name}"
                lines.append((f"VIDEO STILL LOST{which} ({now - self.lost[name]:.0f} s)" + (": the vehicle is held" if self.held else ""), True))
            elif ok and name in self.lost:
                which = "video" if name is None else f"video from camera {name}"
                lines.append((f"{which} back after {now - self.lost.pop(name):.1f} s (the gap is marked in the run)", False))
                if self.held and not self.lost:
                    lines.append(self._resume())
        if lines and self.view is not None:
            try:
                self.view.publish_status({"alert": " | ".join(text for text, _ in lines), "video_ok": not self.lost})
            except Exception:  # noqa: BLE001 - the view is cosmetic; the console said it
                pass
        return lines

    def _lost(self, name: str | None, status: Any, n_cameras: int, n_ok: int, now: float) -> list[tuple[str, bool]]:
        self.lost[name] = now
        self._last_said[name] = now
        self.losses += 1
        hint = "" if self.hold else " (fly --on-video-loss hold would hold the vehicle until frames return)"
        if name is None:
            text = (f"VIDEO LOST at waypoint {status.waypoint}/{status.waypoints}: no frame from the camera; "
                    "waypoints flown now have no images and must be flown again" + hint)
        else:
            text = (f"VIDEO LOST FROM CAMERA {name} at waypoint {status.waypoint}/{status.waypoints}: no frame from it "
                    f"({n_ok} of {n_cameras} cameras still recording); waypoints flown now have no images from {name} "
                    "and must be flown again for it" + hint)
        lines = [(text, True)]
        if self.hold and not self.held and status.armed and status.mode in ("AUTO", "AUTO.MISSION"):  # ArduCopter's, PX4's
            self.held = self._set_mode("GUIDED")
            lines.append(("held: GUIDED at its position until frames return (--on-video-loss hold)", False) if self.held
                         else ("HOLD REFUSED by the vehicle: it flies on in AUTO; take over to hold it", True))
        return lines

    def _resume(self) -> tuple[str, bool]:
        self.held = False
        if self._set_mode("AUTO"):
            return "resumed: AUTO continues the mission", False
        return "AUTO REFUSED: the vehicle still holds in GUIDED; switch to AUTO to go on", True

    def _set_mode(self, mode: str) -> bool:
        from dronecal_field.errors import LinkError
        from dronecal_field.mavlink import ardupilot as ap

        try:
            return self.link.set_mode(mode, timeout_s=2.0) == ap.MAV_RESULT_ACCEPTED
        except LinkError:
            return False
