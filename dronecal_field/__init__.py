"""dronecal-field: calibrate hard-to-reach fixed cameras with an RTK drone and a marker.

Stages (one module or package each): ``core`` (camera model, calibration,
uncertainty), ``geodesy``, ``plan``, ``mavlink`` (link, mission protocol,
flight), ``runfile`` (the MCAP run contract), ``sim`` (vehicle and camera
simulators), ``pipeline`` (offline calibration of a run), ``survey``.
See docs/conventions.md for frames, units and names.
"""

__version__ = "0.1.0"
