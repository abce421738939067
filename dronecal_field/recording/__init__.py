"""The recorder behind ``dronecal-field fly``: capture threads, bounded queues, live status.

``recorder.Recorder`` records one run (MCAP + .tlog) from a MAVLink link and a
video source; ``status`` holds the pure conversions and the status line;
``marker_check`` is the cheap once-a-second "is the marker in view" probe.
"""
