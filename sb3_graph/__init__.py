"""sb3-graph: graph neural network policies, compact graph buffers and graph defaults for
Stable-Baselines3 and sb3-contrib algorithms (TD3, DDPG, SAC, TQC, CrossQ, PPO, A2C)."""

from sb3_graph.a2c import A2C
from sb3_graph.batching import GraphBatch, batch_to_padded, padded_to_batch
from sb3_graph.buffers import GraphReplayBuffer, GraphRolloutBuffer
from sb3_graph.cloning import Demonstrations, behaviour_clone
from sb3_graph.crossq import CrossQ, GraphCrossQCritic, GraphCrossQPolicy
from sb3_graph.ddpg import DDPG
from sb3_graph.layers import RelationalMaxConv
from sb3_graph.networks import GraphCritic, GraphQNetwork, GraphTrunk
from sb3_graph.ppo import PPO, GraphActorCriticPolicy
from sb3_graph.sac import SAC, GraphSACActor, GraphSACPolicy
from sb3_graph.spaces import GraphSpace
from sb3_graph.td3 import TD3, GraphActor, GraphPolicy, GraphTD3Policy
from sb3_graph.toy_envs import MAX_NEIGHBOUR_ID  # registers the toy task: gym.make("GraphMaxNeighbour-v0")
from sb3_graph.tqc import TQC, GraphQuantileCritic, GraphTQCPolicy

__version__ = "0.1.0"

#: Every graph policy class of the package (e.g. for an allow-list of classes that a saved
#: planner may name).
POLICY_CLASSES = (GraphPolicy, GraphSACPolicy, GraphTQCPolicy, GraphCrossQPolicy, GraphActorCriticPolicy)

__all__ = [
    "A2C",
    "DDPG",
    "PPO",
    "POLICY_CLASSES",
    "SAC",
    "TD3",
    "TQC",
    "CrossQ",
    "GraphActor",
    "GraphActorCriticPolicy",
    "GraphBatch",
    "GraphCritic",
    "GraphCrossQCritic",
    "GraphCrossQPolicy",
    "GraphPolicy",
    "GraphQNetwork",
    "GraphQuantileCritic",
    "GraphReplayBuffer",
    "GraphRolloutBuffer",
    "GraphSACActor",
    "GraphSACPolicy",
    "GraphSpace",
    "GraphTD3Policy",
    "GraphTQCPolicy",
    "GraphTrunk",
    "MAX_NEIGHBOUR_ID",
    "RelationalMaxConv",
    "__version__",
    "batch_to_padded",
    "behaviour_clone",
    "Demonstrations",
    "padded_to_batch",
]
