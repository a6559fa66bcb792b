"""Graph layers of the relational policy networks: the convolution
(:mod:`~sb3_graph.common.layers.relational_max_conv`), its kernel layouts
(:mod:`~sb3_graph.common.layers.layouts`), the max aggregation's autograd functions
(:mod:`~sb3_graph.common.layers.max_aggregation`) and the switch of their compiled CPU kernels
(:mod:`~sb3_graph.common.layers.compiled`)."""

from sb3_graph.common.layers.compiled import use_compact_rows, use_compiled_kernels
from sb3_graph.common.layers.layouts import (
    CompactLayout,
    EdgeLayout,
    RelationalLayout,
    check_edges,
    compact_layout,
    edge_layout,
    relational_layout,
)
from sb3_graph.common.layers.max_aggregation import SegmentMax, segment_max
from sb3_graph.common.layers.relational_max_conv import AGGREGATIONS, RelationalMaxConv, relational_conv

__all__ = [
    "AGGREGATIONS",
    "CompactLayout",
    "EdgeLayout",
    "RelationalLayout",
    "RelationalMaxConv",
    "SegmentMax",
    "check_edges",
    "compact_layout",
    "edge_layout",
    "relational_conv",
    "relational_layout",
    "segment_max",
    "use_compact_rows",
    "use_compiled_kernels",
]
