"""``plan``: from what a surveyor knows about a pole camera to a flyable mission.

Modules, in the order the stage uses them:

- ``site``: the inputs (site file keys = CLI flags), the intrinsics guess from
  whatever the datasheet gives, the guessed :class:`~dronecal_field.core.camera.Camera`.
- ``strategies``: scoring of the candidates: the image-space layouts of
  ``dronecal_field.sampling`` (region of interest, targets over its image
  area, predicted ROI error) and the paper's strategies (re-exported from
  ``sampling.lattice``, the one home that ``survey`` uses too).
- ``route``: point order, keep-out detours, the flight-time model.
- ``mission``: mission items and the files (QGC ``.plan``, ``QGC WPL 110``,
  GeoJSON) plus the JSON schema of the ``.plan`` subset we emit.
- ``preview``: the preview figure.
- ``stage``: ``make_plan`` (pure, returns a report) and ``write_plan``
  (atomic folder write).

Frames are those of docs/conventions.md; the grid is built in the *site frame*
(X along the camera azimuth, Y left, Z up, origin at the pole's foot).
"""
