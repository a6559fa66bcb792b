"""CrossQ (sb3-contrib) with graph defaults and batch-renormalized graph critics."""

from sb3_graph.crossq.crossq import CrossQ
from sb3_graph.crossq.policies import GraphCrossQCritic, GraphCrossQPolicy

__all__ = ["CrossQ", "GraphCrossQCritic", "GraphCrossQPolicy"]
