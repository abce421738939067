"""Offline calibration of a run file (``dronecal-field calibrate``).

Stages, each a module of pure functions on arrays except ``run`` and ``report``:
``hover`` (hover windows from events, MISSION_ITEM_REACHED or the GNSS track),
``sampling`` (which frames to decode), ``detect`` (ArUco and LED detection),
``align`` (camera-vs-GNSS time offset), ``points`` (robust per-waypoint 3D-2D
points with measured sigmas), ``maps`` (model choice, uncertainty over the
image, ground homography), ``run`` (the stage function ``calibrate_run``),
``report``/``figures``/``annotate`` (the output files). See docs/calibrate.md.
"""
