"""TQC (sb3-contrib) with graph defaults, its graph policy and quantile critics."""

from sb3_graph.tqc.policies import GraphQuantileCritic, GraphTQCPolicy
from sb3_graph.tqc.tqc import TQC

__all__ = ["TQC", "GraphQuantileCritic", "GraphTQCPolicy"]
