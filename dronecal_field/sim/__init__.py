"""Simulators for tests, the demo and field rehearsals.

``vehicle``: an ArduCopter stand-in speaking MAVLink 2 (mission server, modes,
kinematic flight, RTK-like GNSS), copying the behaviours recorded from
ArduCopter 4.7 SITL in ``shared/replays/arducopter-sitl``.
The simulated camera lives beside it and follows the vehicle over MAVLink.
"""
