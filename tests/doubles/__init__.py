"""Test doubles that inject faults for real (never in a shipped package).

A config names them by entry point, e.g. ``env.suite=tests.doubles.envs:FaultyMarkerEnv``;
Ray workers import them from the repository root (the driver's working directory, which Ray
puts on its workers' path), as the CLI subprocess tests do from their cwd.
"""
