"""Backward-compatible home of :mod:`sb3_graph.common.buffers`.

Models saved before the move name ``sb3_graph.buffers.GraphReplayBuffer`` as their pickled
``replay_buffer_class`` (e.g. the repository's shipped pretrained planners): this module keeps
them loading.
"""

from sb3_graph.common.buffers import GraphReplayBuffer, GraphRolloutBuffer

__all__ = ["GraphReplayBuffer", "GraphRolloutBuffer"]
