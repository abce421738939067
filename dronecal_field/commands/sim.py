"""``dronecal-field sim vehicle|camera``: the simulators, for tests, the demo and rehearsals."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sim", help="run the SITL-style vehicle or the simulated camera")
    sims = parser.add_subparsers(dest="sim_command", metavar="SIMULATOR", required=True)
    from dronecal_field.commands import sim_camera, sim_vehicle

    for module in (sim_vehicle, sim_camera):
        module.register(sims)
