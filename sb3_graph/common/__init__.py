"""The neural-net core that every algorithm of the package shares, as SB3's ``common/``: the graph
observation space, ragged batches, the relational layers, the networks, the per-vertex
distributions, the graph buffers, the algorithm mixin and behaviour cloning."""
