"""Live calibration during ``fly``: what the pilot learns before landing (issue 13).

* ``progress.py``: the pure core, per waypoint (detections -> 3D-2D point,
  running calibration, coverage, verdict); no threads, no I/O.
* ``refly.py``: the mission of the waypoints to fly again.
* ``worker.py``: the recorder's observer and the worker thread around the core.
* ``view.py``: the Foxglove WebSocket that shows it all.
"""
