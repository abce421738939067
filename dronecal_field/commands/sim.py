"""``dronecal-field sim vehicle|camera``: the simulators, for tests, the demo and rehearsals."""

from __future__ import annotations

import argparse
import importlib


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sim", help="run the SITL-style vehicle or the simulated camera")
    sims = parser.add_subparsers(dest="sim_command", metavar="SIMULATOR", required=True)
    for name in ("sim_vehicle", "sim_camera"):
        try:
            module = importlib.import_module(f"dronecal_field.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"dronecal_field.commands.{name}":
                continue
            raise
        module.register(sims)
