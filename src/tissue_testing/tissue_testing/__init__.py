"""Test and tooling support for the workspace: start the installed nodes as real processes on an
isolated DDS domain (:mod:`.harness`) and run the whole graph against a bag (:mod:`.system_graph`).

Used by the tests, the demo, the bag generator and the system benchmarks; it finds the workspace
(``install/``, ``bags/``) from its own source location, so it serves a colcon workspace built with
``--symlink-install`` (what ``scripts/setup.sh`` does).
"""
