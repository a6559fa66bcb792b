"""The relational graph convolution of the policy networks, :class:`RelationalMaxConv`, and its
functional form :func:`relational_conv`, which picks the kernel and layout of each call."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch_geometric.nn import MessagePassing

from sb3_graph.common.layers.compiled import _COMPILED, _compiled_path
from sb3_graph.common.layers.layouts import CompactLayout, compact_layout, edge_layout, relational_layout
from sb3_graph.common.layers.max_aggregation import _CompactRelationalConv, _RelationalMax, segment_max

AGGREGATIONS = ("max", "mean", "sum")


# Without autograd, one convolution computes every relation row in one fused matmul (its weights
# fused once per parameter change, see RelationalMaxConv.inference_weights) below this many
# vertices, and only the rows that edges read from it on: per call, fused / compact 0.09 / 0.18 ms
# at 4 vertices (a planner's scene), 0.29 / 0.27 ms at 560, 3.5 / 2.8 ms at 5,238 (a batch of 256
# intersection graphs: the target networks); 1 thread, 64 channels, 2 relations.
_COMPACT_MIN_VERTICES = 256


class RelationalMaxConv(MessagePassing):
    r"""Relational graph convolution that aggregates *transformed* messages per relation
    (Klimke et al., IEEE IV 2022, section "Network Architecture"):

    .. math::
        \mathbf{x}^{\prime}_i = \mathbf{W}_0 \mathbf{x}_i + \mathbf{b}
        + \sum_{r \in \mathcal{R}} \bigoplus_{j \in \mathcal{N}_r(i)} \mathbf{W}_r \mathbf{x}_j

    and, with edge features :math:`\mathbf{e}_{ji}` (``edge_dim > 0``), the message of edge
    :math:`j \to i` is :math:`\mathbf{W}_r \mathbf{x}_j + \mathbf{U}_r \mathbf{e}_{ji}`, still
    reduced after the transform (the maximum over these messages, per relation),

    where :math:`\bigoplus` is the element-wise maximum (or mean / sum) over the in-neighbours
    :math:`\mathcal{N}_r(i)` of vertex :math:`i` along edges of relation :math:`r`, and an empty
    neighbourhood contributes :math:`\mathbf{0}`: a vertex without incoming edges reduces to a
    dense layer on itself. Unlike :class:`torch_geometric.nn.conv.RGCNConv` with ``aggr="max"``,
    which computes :math:`\mathbf{W}_r \max_j \mathbf{x}_j`, the maximum is taken after the
    relation weight is applied. No activation is applied (PyG style): the model applies it.

    The relation transforms and the root transform are one matmul to ``(N, (R + 1) * out)``; each
    edge then reads the row of its own relation and the messages are reduced into ``N * R``
    segments ``target * R + relation`` (:func:`relational_conv`, which also runs several
    convolutions of the same shape at once, e.g. twin critics). On the compiled CPU path with
    autograd, for stacked convolutions and for batches of 256 vertices or more, only the relation
    rows that some edge reads are computed (:class:`_CompactRelationalConv`, :func:`use_compact_rows`).

    :param in_channels: size of each input vertex feature
    :param out_channels: size of each output vertex feature
    :param num_relations: number of edge types :math:`R`
    :param aggr: aggregation within one relation: ``"max"`` (paper), ``"mean"`` or ``"sum"``
    :param root_weight: add the root term :math:`\mathbf{W}_0 \mathbf{x}_i`
    :param bias: add a learnable bias :math:`\mathbf{b}`
    :param edge_dim: number of edge features :math:`D` (0: messages read vertex features only)

    Shapes:
        - **input:** vertex features :math:`(|\mathcal{V}|, F_{in})`, edge indices
          :math:`(2, |\mathcal{E}|)` with rows ``(source, target)``, edge types
          :math:`(|\mathcal{E}|)`, edge features :math:`(|\mathcal{E}|, D)` when ``edge_dim > 0``
        - **output:** vertex features :math:`(|\mathcal{V}|, F_{out})`

    Without edge features, repeated edges are merged for the maximum and the aggregation runs
    over per-vertex rows (a message is a row of :math:`\mathbf{x} \mathbf{W}_r`); with them, every
    edge carries its own message. On CPU the max aggregation runs in compiled kernels
    (:mod:`sb3_graph.common.layers._max_kernel`, numba), which also add the bias and, with edge features, form
    each edge's message as they reduce; :func:`use_compiled_kernels` switches them off for the
    PyTorch formulation, the reference they are tested against (with edge features it builds the
    ``(E, F_out)`` messages and reduces them with :func:`segment_max`).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        num_relations: int,
        aggr: str = "max",
        root_weight: bool = True,
        bias: bool = True,
        edge_dim: int = 0,
    ) -> None:
        if edge_dim < 0:
            raise ValueError(f"RelationalMaxConv: edge_dim must be >= 0, got {edge_dim}")
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
        self.edge_dim = int(edge_dim)
        self.edge_weight = (
            nn.Parameter(torch.empty(num_relations, edge_dim, out_channels)) if edge_dim else None
        )
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
        if self.edge_weight is not None:
            edge_bound = 1.0 / math.sqrt(self.edge_dim)
            nn.init.uniform_(self.edge_weight, -edge_bound, edge_bound)

    def forward(self, x: Tensor, edge_index: Tensor, edge_type: Tensor, edge_attr: Tensor | None = None) -> Tensor:
        """
        :param x: ``(N, in_channels)`` vertex features
        :param edge_index: ``(2, E)`` long ``(source, target)`` rows
        :param edge_type: ``(E,)`` long relation ids in ``[0, num_relations)``
        :param edge_attr: ``(E, edge_dim)`` edge features (required iff ``edge_dim > 0``)
        :return: ``(N, out_channels)`` vertex features
        """
        return relational_conv([self], x, edge_index, edge_type, edge_attr)

    def inference_weights(self) -> tuple[Tensor, Tensor | None]:
        """The fused weight and bias of :func:`relational_conv` for this convolution alone, for
        use without autograd (their values, not a graph to the parameters).

        Fusing is ~10 small tensor operations, as costly as the layer's matmul at intersection
        sizes (~13 vertices), so the result is kept until a parameter changes: another tensor
        (assignment), an in-place update (version counter: optimizer steps, Polyak updates,
        ``load_state_dict``) or new storage, type or device (``.to()``, ``.double()``).

        :return: as :func:`_fused_weights` with ``stacked=False``
        """
        params = [self.weight] + ([self.root.weight] if self.root is not None else []) + [self.bias]
        key = tuple(None if p is None else (id(p), p._version, p.data_ptr(), p.dtype, p.device) for p in params)
        cached = self.__dict__.get("_inference_weights")
        if cached is None or cached[0] != key:
            # Plain tensors even when called in inference mode: usable in any later no-grad pass.
            with torch.inference_mode(False), torch.no_grad():
                fused = _fused_weights([self], stacked=False)
            # The parameters themselves are held so that their ids stay theirs while cached.
            cached = (key, fused, params)
            self.__dict__["_inference_weights"] = cached
        return cached[1]

    def message(self, x_j: Tensor) -> Tensor:
        return x_j

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}({self.in_channels}, {self.out_channels}, "
            f"num_relations={self.num_relations}, aggr={self.aggr!r}"
            + (f", edge_dim={self.edge_dim})" if self.edge_dim else ")")
        )


def relational_conv(
    convs: Sequence[RelationalMaxConv],
    x: Tensor,
    edge_index: Tensor,
    edge_type: Tensor,
    edge_attr: Tensor | None = None,
) -> Tensor:
    """Apply one convolution, or ``K`` convolutions of the same shape each to its own input, on one
    graph batch: one (batched) matmul and one aggregation for all of them (the ``K`` copies are
    ``K`` disjoint graphs).

    :param convs: ``K`` convolutions with equal channels, relations, aggregation, root, bias and
        edge features
    :param x: ``(N, in_channels)`` input of the single convolution (``K = 1``), or
        ``(K, N, in_channels)`` input of each convolution
    :param edge_index: ``(2, E)`` long ``(source, target)`` rows
    :param edge_type: ``(E,)`` relation ids
    :param edge_attr: ``(E, edge_dim)`` edge features, required iff the convolutions have ``edge_dim > 0``
    :return: ``(N, out_channels)`` or ``(K, N, out_channels)``, as ``x``
    """
    first = convs[0]
    stacked = x.dim() == 3
    copies, num_nodes = len(convs), x.size(-2)
    if not stacked and copies != 1:
        raise ValueError(f"relational_conv: x must be (K, N, in_channels) for {copies} convolutions")
    r, out, has_root = first.num_relations, first.out_channels, first.root is not None
    stride = r + 1 if has_root else r
    compiled = first.aggr == "max" and first.bias is not None and _compiled_path(x)
    large = stacked or torch.is_grad_enabled() or num_nodes >= _COMPACT_MIN_VERTICES
    if first.edge_dim:
        if edge_attr is None or edge_attr.shape != (edge_index.size(1), first.edge_dim):
            got = None if edge_attr is None else tuple(edge_attr.shape)
            raise ValueError(
                f"relational_conv: edge_attr of shape ({edge_index.size(1)}, {first.edge_dim}) is required, got {got}"
            )
        # The kernels add each edge's term as they reduce; features that need a gradient take the
        # PyTorch formulation (observations never do), and so does a planner's scene without
        # autograd (0.92 against 0.66 ms per call at 19 vertices, see _COMPACT_MIN_VERTICES).
        if compiled and _COMPILED["compact"] and large and not edge_attr.requires_grad:
            compact = compact_layout(edge_index, edge_type, num_nodes, r, stride, copies, per_edge=True)
            order = compact.base.edge_order
            attr = (edge_attr if order is None else edge_attr.index_select(0, order)).to(x.dtype).contiguous()
            return _compact_conv(convs, x, compact, attr)
        if stacked:
            return torch.stack(
                [_edge_conv(c, x[k], edge_index, edge_type, edge_attr) for k, c in enumerate(convs)]
            )
        return _edge_conv(first, x, edge_index, edge_type, edge_attr)
    if compiled and _COMPILED["compact"] and large:
        return _compact_conv(convs, x, compact_layout(edge_index, edge_type, num_nodes, r, stride, copies), None)
    if stacked or torch.is_grad_enabled():
        # The kernel adds the bias itself: no fused bias to build on the compiled path.
        weight, bias = _fused_weights(convs, stacked, with_bias=not compiled)
    else:  # inference: the same tensors, fused once per change of the parameters
        weight, bias = first.inference_weights()
    layout = relational_layout(edge_index, edge_type, num_nodes, r, stride, first.aggr, copies)
    shape = (copies, num_nodes, out) if stacked else (num_nodes, out)
    if compiled:
        # The kernel adds the bias: a plain matmul spares addmm's pass that first copies the
        # broadcast bias into its (N, (R + 1) * out) result.
        kernel_bias = first.bias if not stacked else torch.stack([c.bias for c in convs])
        rows = torch.matmul(x, weight).view(copies * num_nodes * stride, out)
        return _RelationalMax.apply(rows, kernel_bias, layout, shape, r, stride)
    if bias is None or not has_root:
        transformed = torch.matmul(x, weight)
    else:
        transformed = torch.addmm(bias, x, weight) if not stacked else torch.baddbmm(bias, x, weight)
    rows = transformed.view(copies * num_nodes * stride, out)
    if first.aggr == "max":
        result = _RelationalMax.apply(rows, None, layout, shape, r, stride)
    else:
        aggregated = rows.new_zeros(copies * num_nodes * r, out)
        aggregated = aggregated.index_add(0, layout.target, rows.index_select(0, layout.source))
        if first.aggr == "mean":
            aggregated = aggregated / layout.counts.clamp(min=1).unsqueeze(-1).to(aggregated.dtype)
        result = aggregated.view(*shape[:-1], r, out).sum(dim=-2)
        if has_root:
            return result + transformed.view(*shape[:-1], stride, out)[..., r, :]
    return result + bias if bias is not None and not has_root else result


def _compact_conv(
    convs: Sequence[RelationalMaxConv], x: Tensor, compact: CompactLayout, attr: Tensor | None
) -> Tensor:
    """:class:`_CompactRelationalConv` of ``K`` convolutions (``attr``: the edge features in the
    layout's edge order, ``None`` without)."""
    has_root, has_edges = convs[0].root is not None, attr is not None
    params = [c.weight for c in convs] + ([c.root.weight for c in convs] if has_root else [])
    params += [c.edge_weight for c in convs] if has_edges else []
    params += [c.bias for c in convs]
    return _CompactRelationalConv.apply(x, attr, compact, len(convs), has_root, has_edges, *params)


def _fused_weights(
    convs: Sequence[RelationalMaxConv], stacked: bool, with_bias: bool = True
) -> tuple[Tensor, Tensor | None]:
    """Weight and bias of :func:`relational_conv`'s one matmul for ``K`` convolutions.

    :param convs: ``K`` convolutions of the same shape, without edge features
    :param stacked: ``(K, in, R * out [+ out])`` and ``(K, 1, ...)`` for a batched matmul; else
        (``K = 1``) ``(in, ...)`` and ``(...,)``
    :param with_bias: build the fused bias (``False``: ``None``, for the compiled path)
    :return: the weight (relation blocks, then the root block) and the bias (0 on the relation
        blocks: it joins the root block, so the matmul adds it), ``None`` without bias
    """
    first = convs[0]
    copies, r, out, has_root = len(convs), first.num_relations, first.out_channels, first.root is not None
    if not stacked:
        # A plain matmul for one convolution: cheaper than a batched one, and 2-D results let the
        # caller apply an in-place activation without autograd's view bookkeeping. Built directly
        # (not as copy 0 of the stacked weight): the same values with fewer tensor operations and
        # autograd nodes, which weigh at small batches.
        weight = first.weight.permute(1, 0, 2).reshape(first.in_channels, r * out)
        if has_root:
            weight = torch.cat((weight, first.root.weight.t()), dim=1)
        if not with_bias or first.bias is None:
            return weight, None
        return weight, torch.cat((first.bias.new_zeros(r * out), first.bias)) if has_root else first.bias
    bias = torch.stack([c.bias for c in convs]).unsqueeze(1) if with_bias and first.bias is not None else None
    weight = torch.stack([c.weight for c in convs]).permute(0, 2, 1, 3).reshape(copies, -1, r * out)
    if has_root:
        weight = torch.cat((weight, torch.stack([c.root.weight for c in convs]).transpose(1, 2)), dim=2)
        if bias is not None:
            bias = torch.cat((bias.new_zeros(copies, 1, r * out), bias), dim=2)
    return weight, bias


def _edge_conv(
    conv: RelationalMaxConv, x: Tensor, edge_index: Tensor, edge_type: Tensor, edge_attr: Tensor
) -> Tensor:
    """One convolution with edge features in the PyTorch formulation (the reference of the compiled
    path, and the path of other devices, other aggregations and features that need a gradient):
    message ``W_r x_j + U_r e_ji`` per edge, reduced per ``(target, relation)`` segment, summed over
    relations, plus root and bias (plain autograd around :func:`segment_max`)."""
    r, out, num_nodes = conv.num_relations, conv.out_channels, x.size(0)
    layout = edge_layout(edge_index, edge_type, num_nodes, r)
    relation_rows = torch.matmul(x, conv.weight.permute(1, 0, 2).reshape(conv.in_channels, r * out))
    messages = relation_rows.view(num_nodes * r, out).index_select(0, layout.source)
    edge_terms = torch.matmul(edge_attr.to(x.dtype), conv.edge_weight.permute(1, 0, 2).reshape(conv.edge_dim, r * out))
    if r == 1:
        messages = messages + edge_terms
    else:
        index = edge_type.long().view(-1, 1, 1).expand(-1, 1, out)
        messages = messages + edge_terms.view(-1, r, out).gather(1, index).squeeze(1)
    if conv.aggr == "max":
        aggregated = segment_max(messages, None, layout.segment, num_nodes * r, layout.num_nonempty)
    else:
        aggregated = messages.new_zeros(num_nodes * r, out).index_add(0, layout.segment, messages)
        if conv.aggr == "mean":
            aggregated = aggregated / layout.counts.clamp(min=1).unsqueeze(-1).to(aggregated.dtype)
    result = aggregated.view(num_nodes, r, out).sum(dim=1)
    if conv.root is not None:
        result = result + conv.root(x)
    return result if conv.bias is None else result + conv.bias
