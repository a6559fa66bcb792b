"""sb3-graph: graph neural network policies, a compact graph replay buffer and TD3 for Stable-Baselines3."""

from sb3_graph.batching import GraphBatch, batch_to_padded, padded_to_batch
from sb3_graph.buffers import GraphReplayBuffer
from sb3_graph.layers import RelationalMaxConv
from sb3_graph.policies import GraphPolicy
from sb3_graph.spaces import GraphSpace
from sb3_graph.td3 import TD3

__version__ = "0.1.0"

__all__ = [
    "TD3",
    "GraphBatch",
    "GraphPolicy",
    "GraphReplayBuffer",
    "GraphSpace",
    "RelationalMaxConv",
    "__version__",
    "batch_to_padded",
    "padded_to_batch",
]
