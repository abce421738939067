"""MAVLink: the link (pymavlink, explicit schemes, signing), the mission
protocol client, mission files, pre-flight checks and flight commands.

Everything here talks to ArduPilot as recorded in
``shared/replays/arducopter-sitl/README.md``; the simulated vehicle in
``dronecal_field.sim.vehicle`` copies the same behaviour.
"""
