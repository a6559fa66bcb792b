"""SAC with graph defaults and its per-vertex squashed-Gaussian graph policy."""

from sb3_graph.sac.policies import GraphSACActor, GraphSACPolicy
from sb3_graph.sac.sac import SAC

__all__ = ["SAC", "GraphSACActor", "GraphSACPolicy"]
