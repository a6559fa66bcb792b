"""Graph layers of the relational policy networks."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch_geometric.nn import MessagePassing

AGGREGATIONS = ("max", "mean", "sum")


class RelationalMaxConv(MessagePassing):
    r"""Relational graph convolution that aggregates *transformed* messages per relation
    (Klimke et al., IEEE IV 2022, section "Network Architecture"):

    .. math::
        \mathbf{x}^{\prime}_i = \mathbf{W}_0 \mathbf{x}_i + \mathbf{b}
        + \sum_{r \in \mathcal{R}} \bigoplus_{j \in \mathcal{N}_r(i)} \mathbf{W}_r \mathbf{x}_j

    where :math:`\bigoplus` is the element-wise maximum (or mean / sum) over the in-neighbours
    :math:`\mathcal{N}_r(i)` of vertex :math:`i` along edges of relation :math:`r`, and an empty
    neighbourhood contributes :math:`\mathbf{0}`: a vertex without incoming edges reduces to a
    dense layer on itself. Unlike :class:`torch_geometric.nn.conv.RGCNConv` with ``aggr="max"``,
    which computes :math:`\mathbf{W}_r \max_j \mathbf{x}_j`, the maximum is taken after the
    relation weight is applied. No activation is applied (PyG style): the model applies it.

    All relation transforms are one matmul to ``(N, R * out_channels)``; each edge then reads the
    row of its own relation and PyG aggregates over the combined index ``target * R + relation``.

    :param in_channels: size of each input vertex feature
    :param out_channels: size of each output vertex feature
    :param num_relations: number of edge types :math:`R`
    :param aggr: aggregation within one relation: ``"max"`` (paper), ``"mean"`` or ``"sum"``
    :param root_weight: add the root term :math:`\mathbf{W}_0 \mathbf{x}_i`
    :param bias: add a learnable bias :math:`\mathbf{b}`

    Shapes:
        - **input:** vertex features :math:`(|\mathcal{V}|, F_{in})`, edge indices
          :math:`(2, |\mathcal{E}|)` with rows ``(source, target)``, edge types
          :math:`(|\mathcal{E}|)`
        - **output:** vertex features :math:`(|\mathcal{V}|, F_{out})`
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        num_relations: int,
        aggr: str = "max",
        root_weight: bool = True,
        bias: bool = True,
    ) -> None:
        if aggr not in AGGREGATIONS:
            raise ValueError(f"RelationalMaxConv: aggr must be one of {AGGREGATIONS}, got {aggr!r}")
        if num_relations < 1:
            raise ValueError(f"RelationalMaxConv: num_relations must be >= 1, got {num_relations}")
        super().__init__(aggr=aggr, node_dim=0)
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.num_relations = num_relations
        self.weight = nn.Parameter(torch.empty(num_relations, in_channels, out_channels))
        self.root = nn.Linear(in_channels, out_channels, bias=False) if root_weight else None
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        super().reset_parameters()
        # Same scale as nn.Linear's default for each relation matrix.
        bound = 1.0 / math.sqrt(self.in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.root is not None:
            self.root.reset_parameters()
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: Tensor, edge_index: Tensor, edge_type: Tensor) -> Tensor:
        """
        :param x: ``(N, in_channels)`` vertex features
        :param edge_index: ``(2, E)`` long ``(source, target)`` rows
        :param edge_type: ``(E,)`` long relation ids in ``[0, num_relations)``
        :return: ``(N, out_channels)`` vertex features
        """
        n, r, out = x.size(0), self.num_relations, self.out_channels
        # (N, R * out) viewed as N * R rows: row j * R + r holds W_r x_j.
        transformed = (x @ self.weight.permute(1, 0, 2).reshape(self.in_channels, r * out)).view(n * r, out)
        edge_type = edge_type.long()
        relational_index = torch.stack((edge_index[0] * r + edge_type, edge_index[1] * r + edge_type))
        # Aggregating into N * R slots keeps the relations apart; empty slots stay 0.
        aggregated = self.propagate(relational_index, x=transformed, size=(n * r, n * r))
        result = aggregated.view(n, r, out).sum(dim=1)
        if self.root is not None:
            result = result + self.root(x)
        if self.bias is not None:
            result = result + self.bias
        return result

    def message(self, x_j: Tensor) -> Tensor:
        return x_j

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
            f"num_relations={self.num_relations}, aggr={self.aggr!r})"
        )
