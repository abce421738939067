"""The MCAP run file (shared/contracts/run-format.md): records, writer, streaming reader.

``records`` holds the domain values, ``writer.RunWriter`` records a run with
crash-safe chunking, ``reader.open_run`` reads any file that follows the
contract (also one cut off mid-chunk), ``tlog.TlogWriter`` writes the standard
MAVLink telemetry log beside it, and ``importer`` builds a run from a flight
log (.tlog or DataFlash .BIN) and a video file. See docs/runfile.md.
"""

from dronecal_field.runfile.records import (
    Attitude,
    Frame,
    GnssFix,
    MarkerSpec,
    RunEvent,
    RunMetadata,
)

__all__ = ["Attitude", "Frame", "GnssFix", "MarkerSpec", "RunEvent", "RunMetadata"]
