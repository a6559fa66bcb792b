"""Test session settings."""

import os
import tempfile


def pytest_configure(config):
    # Checkpoint signatures (sb3_graph.signing) use a key of the test session, not the user's.
    if not os.environ.get("SB3_GRAPH_KEY_FILE"):
        os.environ["SB3_GRAPH_KEY_FILE"] = os.path.join(tempfile.mkdtemp(prefix="sb3-graph-key-"), "file-key")
