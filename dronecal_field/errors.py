"""The error hierarchy. Library code raises these; only the CLI prints them.

Every message names the offending value and says what to do, in one line.
"""

from __future__ import annotations


class DronecalError(Exception):
    """Base class: a problem the user can fix. The CLI prints it and exits 2."""


class InputError(DronecalError):
    """A file, flag or value that cannot be used as given."""


class DegenerateGeometryError(DronecalError):
    """3D-2D pairs that cannot determine a camera (too few, coplanar, behind it)."""


class CalibrationError(DronecalError):
    """The solver could not reach a trustworthy camera."""


class ContractError(InputError):
    """A run file that breaks shared/contracts/run-format.md."""


class PlanError(DronecalError):
    """No safe, useful mission exists for the site and limits given."""


class LinkError(DronecalError):
    """The MAVLink link or the vehicle did not answer as the protocol requires."""


class MissionRejectedError(LinkError):
    """The vehicle refused the mission upload or it read back differently."""


class PreflightError(DronecalError):
    """A pre-arm check failed; nothing was commanded."""


class VideoError(DronecalError):
    """The video source could not be opened or stopped producing frames."""


class RecordingStoppedError(DronecalError):
    """Writing a recording stopped (a full disk): the file keeps what was written before, finalised."""
