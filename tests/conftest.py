"""Test session settings."""

import os
import tempfile
from pathlib import Path

import pytest


def pytest_configure(config):
    # Checkpoint signatures (sb3_graph.files.signing) use a key of the test session, not the user's.
    if not os.environ.get("SB3_GRAPH_KEY_FILE"):
        os.environ["SB3_GRAPH_KEY_FILE"] = os.path.join(tempfile.mkdtemp(prefix="sb3-graph-key-"), "file-key")
    # The checkout's entry points (its domain plug-ins), whatever copy of the package is installed.
    from checkout_entry_points import install

    install(Path(__file__).parents[1], Path(tempfile.mkdtemp(prefix="sb3-graph-entry-points-")))


@pytest.fixture(scope="module")
def service():
    """The PR planner's service on the 4-way layout, for the serve tests' in-thread servers."""
    from envs.serve.app import PlannerService

    return PlannerService("pr", "CoopIntersection4Way-v0")
