"""The paper's graph input representation: vertex features ``[s, v, d]``, same-lane and crossing edges.

Vertices are the vehicles of a :class:`~envs.simulation.scene.Scene` in row order (row ``i`` = vertex ``i`` =
action slot ``i``). Features (paper, "Input Representation"):

- ``s``: path coordinate [m] (``Scene.s``): 0 where the path leaves the intersection area,
  ``-s_ref`` where it enters (default ``s_ref`` = 25 m), with the part inside the intersection
  scaled to ``s_ref``; multiplied by ``s_scale`` (default ``DEFAULT_S_SCALE`` = 1/25 m: ``s`` in
  units of the default ``s_ref``, so all three features are of order 1 for the network),
- ``v``: speed over the speed limit of the current lane,
- ``d``: inverse of the smallest Mahalanobis distance (paper eq. 2, ``l`` = 5 m, ``w`` = 2 m,
  covariance rotated by the vehicle's own heading) to any other vehicle, clipped to
  ``[0, d_max]`` (default 10, reached when the other vehicle's centre is within a tenth of the
  ellipse); 0 when the vehicle is alone.

Edges (relation ids):

- ``SAME_LANE`` (0): leader -> follower, from each vehicle's nearest predecessor on its path,
- ``CROSSING`` (1): both directions between vehicles on conflicting routes (paths cross or merge,
  ``Scene.conflicts``) that have both not yet left the intersection area
  (``Scene.approaching``: rear before the exit).

When the edges outnumber the space's ``max_edges``, all same-lane edges are kept first and then the
crossing edges between the closest vehicle pairs.

Optional vertex features (config ``vertex_features``, any of :data:`VERTEX_FEATURES`, in the order
given, after ``[s, v, d]``): what AIM and the shield know about a vehicle and the paper's three
features do not say:

- ``"maneuver"``: one-hot ``[left, straight, right]`` (3 columns),
- ``"priority"``: 1 on the major road, 0 on the minor one,
- ``"limit"``: the lane's speed limit over 10 m/s (the road's limit on straight lanes),
- ``"line"``: metres from the front to the stop line (``Scene.dist_to_entry``) times ``s_scale``,
  clipped to ``[-1, 4]`` (negative once past it),
- ``"zone"``: metres from the centre to where the body reaches its route's first conflict zone (padded by
  the shield's ``ZONE_MARGIN``) times ``s_scale``, clipped to ``[-1, 4]`` (4 for a route without any),
- ``"committed"``: 1 when braking at ``a_max`` can no longer stop the body before that zone, or the
  vehicle has left its last zone (the shield's :meth:`~envs.planners.shield.Shield.committed`), else 0,
- ``"human"``: 1 for a human-driven vehicle (``Scene.human``: it follows the static priority rules and
  ignores the planner's command), else 0.

``zone`` and ``committed`` need the scene's layout (every simulated scene has it).

Optional edge features (config ``edge_features``, any of :data:`EDGE_FEATURES`, in the order given),
for edge ``j -> i`` (message from ``j`` to ``i``):

- ``"distance"``: ``|p_j - p_i|`` [m] times ``s_scale`` (units of 25 m by default, like ``s``),
- ``"bearing"``: direction of ``p_j`` seen from vehicle ``i``, relative to ``i``'s heading, in
  ``[-1, 1]`` (radians / pi: 0 straight ahead, +-1 behind, positive to the left),
- ``"zone_receiver"``, ``"zone_sender"``: on a crossing edge, metres from the centre of ``i``
  (receiver) or ``j`` (sender) to where its body reaches the two routes' conflict zone (the shield's
  entry arc, padded by ``ZONE_MARGIN``), times ``s_scale``, clipped to ``[-1, 4]``; 0 where the two
  routes have no conflict zone (same-lane edges of one route). The pair says who reaches the zone
  first (needs the scene's layout).
"""

from __future__ import annotations

import numpy as np
import torch

from envs.simulation.layouts import ZONE_MARGIN, body_hull
from envs.simulation.scene import LEFT, MAJOR, RIGHT, STRAIGHT, Scene
from sb3_graph.common.batching import GraphBatch
from sb3_graph.common.spaces import GraphSpace

# s in units of the default s_ref (25 m): the GNN's inputs stay of order 1.
DEFAULT_S_SCALE = 0.04
SAME_LANE, CROSSING = 0, 1
EDGE_FEATURES = ("distance", "bearing", "zone_receiver", "zone_sender")
NUM_RELATIONS = 2
NODE_FEATURES = 3  # the paper's [s, v, d]
# Optional vertex features and the columns each adds (config ``vertex_features``).
VERTEX_FEATURES = {"maneuver": 3, "priority": 1, "limit": 1, "line": 1, "zone": 1, "committed": 1, "human": 1}
# Distances past this many units of s_scale (100 m by default) look the same to the network.
DISTANCE_CLIP = (-1.0, 4.0)
LIMIT_SCALE = 0.1  # 1 / (10 m/s)
MAHALANOBIS_LENGTH = 5.0
MAHALANOBIS_WIDTH = 2.0


def mahalanobis_matrix(
    position: np.ndarray,
    heading: np.ndarray,
    l: float = MAHALANOBIS_LENGTH,  # noqa: E741 (the paper's symbol)
    w: float = MAHALANOBIS_WIDTH,
) -> np.ndarray:
    """Pairwise Mahalanobis distances of the paper's eq. 2.

    .. math::
        d_{ij} = \\sqrt{(p_j - p_i)^T \\Sigma_i^{-1} (p_j - p_i)},\\quad
        \\Sigma_i = R_{\\psi_i} \\mathrm{diag}(l^2/4, w^2/4) R_{\\psi_i}^T

    :param position: ``(n, 2)`` positions
    :param heading: ``(n,)`` headings [rad]
    :param l: standardized vehicle length [m]
    :param w: standardized vehicle width [m]
    :return: ``(n, n)`` distances, row ``i`` measured in vehicle ``i``'s frame; ``inf`` on the diagonal
    """
    delta = position[None, :, :] - position[:, None, :]  # (i, j, 2): p_j - p_i
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    lon = delta[..., 0] * c + delta[..., 1] * s
    lat = -delta[..., 0] * s + delta[..., 1] * c
    d = np.sqrt(4.0 * lon**2 / l**2 + 4.0 * lat**2 / w**2)
    np.fill_diagonal(d, np.inf)
    return d


def min_mahalanobis(scene: Scene) -> np.ndarray:
    """``(n,)`` smallest Mahalanobis distance from each vehicle to any other (``inf`` when alone)."""
    if scene.num_vehicles < 2:
        return np.full(scene.num_vehicles, np.inf)
    return mahalanobis_matrix(scene.position, scene.heading).min(axis=1)


def num_node_features(vertex_feature_names: tuple[str, ...] | list[str] = ()) -> int:
    """Columns of the vertex features: the paper's 3 plus those of the optional ones.

    :param vertex_feature_names: names among :data:`VERTEX_FEATURES` (config ``vertex_features``)
    :raises ValueError: an unknown name
    """
    unknown = [name for name in vertex_feature_names if name not in VERTEX_FEATURES]
    if unknown:
        raise ValueError(f"vertex feature {unknown[0]!r} is unknown; choose from {list(VERTEX_FEATURES)}")
    return NODE_FEATURES + sum(VERTEX_FEATURES[name] for name in vertex_feature_names)


def zone_arc(scene: Scene) -> np.ndarray:
    """``(n,)`` centre arc at which each body reaches its route's first conflict zone, padded by
    ``ZONE_MARGIN`` (the shield's ``hull_start``); ``inf`` for a route without any.

    :raises ValueError: a scene without its layout or arcs (hand-built)
    """
    _needs_layout(scene)
    return body_hull(scene.layout, scene.route, scene.length)[0]


def committed(scene: Scene) -> np.ndarray:
    """``(n,)`` bool: the shield's rule (:func:`envs.simulation.commitment.committed_vehicles`): braking at
    ``a_max`` can no longer stop the body before its first zone, or it has left its last one.

    :raises ValueError: a scene without its layout or arcs (hand-built)
    """
    from envs.simulation.commitment import committed_vehicles  # compiled (numba): loaded only when asked for

    _needs_layout(scene)
    return committed_vehicles(scene)


def _needs_layout(scene: Scene) -> None:
    if scene.layout is None or scene.arc is None:
        raise ValueError("the zone features need the scene's layout and arcs (every simulated scene has them)")


def _distance_feature(metres: np.ndarray, s_scale: float) -> np.ndarray:
    return np.clip(metres * s_scale, *DISTANCE_CLIP)


def node_features(
    scene: Scene,
    s_scale: float = DEFAULT_S_SCALE,
    d_max: float = 10.0,
    min_distance: np.ndarray | None = None,
    vertex_feature_names: tuple[str, ...] | list[str] = (),
) -> np.ndarray:
    """``(n, num_node_features(vertex_feature_names))`` float32 vertex features: ``[s, v, d]`` and
    the optional ones named (see the module docstring).

    :param scene: the vehicles
    :param s_scale: factor applied to ``s`` and to the distance features
    :param d_max: upper clip of ``d``
    :param min_distance: precomputed :func:`min_mahalanobis` (saves one pairwise pass)
    :param vertex_feature_names: optional features among :data:`VERTEX_FEATURES`, in the order wanted
    :raises ValueError: an unknown name, or a zone feature of a scene without its layout
    """
    if min_distance is None:
        min_distance = min_mahalanobis(scene)
    with np.errstate(divide="ignore"):
        d = np.minimum(1.0 / min_distance, d_max)
    v = scene.speed / scene.speed_limit
    columns = [scene.s * s_scale, v, d]
    num_node_features(vertex_feature_names)
    for name in vertex_feature_names:
        if name == "maneuver":
            columns += [scene.maneuver == LEFT, scene.maneuver == STRAIGHT, scene.maneuver == RIGHT]
        elif name == "priority":
            columns.append(scene.priority == MAJOR)
        elif name == "limit":
            columns.append(scene.speed_limit * LIMIT_SCALE)
        elif name == "line":
            columns.append(_distance_feature(scene.dist_to_entry, s_scale))
        elif name == "zone":
            with np.errstate(invalid="ignore"):  # inf - arc: a route without zones
                columns.append(_distance_feature(zone_arc(scene) - scene.arc, s_scale))
        elif name == "committed":
            columns.append(committed(scene))
        elif name == "human":
            columns.append(scene.humans)
    return np.stack(columns, axis=1).astype(np.float32)


def edges(scene: Scene, max_edges: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Same-lane and crossing edges of a scene.

    :param scene: the vehicles
    :param max_edges: keep at most this many (same-lane first, then the closest crossing pairs)
    :return: ``edge_index`` ``(2, e)`` int64 ``(source, target)`` and ``edge_type`` ``(e,)`` int64
    """
    follower = np.flatnonzero(scene.leader >= 0)
    same = np.stack([scene.leader[follower], follower])
    approaching = scene.approaching
    cross = (
        scene.conflicts[scene.route[:, None], scene.route[None, :]]
        & approaching[:, None]
        & approaching[None, :]
    )
    src, dst = np.nonzero(cross)  # symmetric matrix: both directions, no self loops (diagonal False)
    if max_edges is not None and same.shape[1] + src.size > max_edges:
        room = max(max_edges - same.shape[1], 0)
        same = same[:, :max_edges]
        dist2 = ((scene.position[src] - scene.position[dst]) ** 2).sum(axis=1)
        # Stable sort keeps (i, j) and (j, i) of equal distance next to each other.
        keep = np.sort(np.argsort(dist2, kind="stable")[:room])
        src, dst = src[keep], dst[keep]
    edge_index = np.concatenate([same, np.stack([src, dst])], axis=1).astype(np.int64)
    edge_type = np.concatenate([np.full(same.shape[1], SAME_LANE), np.full(src.size, CROSSING)]).astype(
        np.int64
    )
    return edge_index, edge_type


def edge_features(
    scene: Scene, edge_index: np.ndarray, names: tuple[str, ...] | list[str], s_scale: float = DEFAULT_S_SCALE
) -> np.ndarray:
    """``(e, len(names))`` float32 features of the edges ``(source, target)`` (see the module docstring).

    :param scene: the vehicles
    :param edge_index: ``(2, e)`` edges
    :param names: features among :data:`EDGE_FEATURES`, in the order wanted
    :param s_scale: factor applied to ``distance``
    """
    src, dst = edge_index
    delta = scene.position[src] - scene.position[dst]  # from the receiving vehicle to the sender
    columns = []
    for name in names:
        if name == "distance":
            columns.append(np.hypot(delta[:, 0], delta[:, 1]) * s_scale)
        elif name == "bearing":
            c, s = np.cos(scene.heading[dst]), np.sin(scene.heading[dst])
            lon = delta[:, 0] * c + delta[:, 1] * s
            lat = -delta[:, 0] * s + delta[:, 1] * c
            columns.append(np.arctan2(lat, lon) / np.pi)
        elif name in ("zone_receiver", "zone_sender"):
            columns.append(_pair_zone(scene, edge_index, receiver=name == "zone_receiver", s_scale=s_scale))
        else:
            raise ValueError(f"edge feature {name!r} is unknown; choose from {EDGE_FEATURES}")
    return np.stack(columns, axis=1).astype(np.float32) if columns else np.zeros((len(src), 0), np.float32)


def _pair_zone(scene: Scene, edge_index: np.ndarray, receiver: bool, s_scale: float) -> np.ndarray:
    """``(e,)`` distance feature from the receiver's (or sender's) centre to where its body reaches the
    conflict zone of the edge's two routes; 0 where the routes have none (same-lane edges)."""
    _needs_layout(scene)
    src, dst = edge_index
    me, other = (dst, src) if receiver else (src, dst)
    start = scene.layout.zone_start[scene.route[me], scene.route[other]]
    metres = start - ZONE_MARGIN - scene.length[me] / 2 - np.asarray(scene.arc)[me]
    return np.where(np.isnan(start), 0.0, _distance_feature(np.nan_to_num(metres), s_scale))


def build_observation(
    scene: Scene,
    space: GraphSpace,
    s_scale: float = DEFAULT_S_SCALE,
    d_max: float = 10.0,
    min_distance: np.ndarray | None = None,
    edge_feature_names: tuple[str, ...] | list[str] = (),
    vertex_feature_names: tuple[str, ...] | list[str] = (),
) -> dict[str, np.ndarray]:
    """Turn any scene into the padded graph observation of ``space`` (what the environment returns).

    :param scene: the vehicles (at most ``space.max_nodes``)
    :param space: a ``GraphSpace`` with ``num_node_features(vertex_feature_names)`` node features, 2
        relations and ``len(edge_feature_names)`` edge features
    :param s_scale: factor applied to the ``s`` feature (and to the ``distance`` edge feature)
    :param d_max: upper clip of the ``d`` feature
    :param min_distance: precomputed :func:`min_mahalanobis`, optional
    :param edge_feature_names: edge features among :data:`EDGE_FEATURES` (config ``edge_features``)
    :param vertex_feature_names: optional vertex features among :data:`VERTEX_FEATURES` (config ``vertex_features``)
    :return: the observation dictionary
    :raises ValueError: when the names do not match the space's number of edge or node features
    """
    arrays = _graph_arrays(
        scene, space, s_scale, d_max, min_distance, edge_feature_names, vertex_feature_names, "build_observation"
    )
    return space.encode(*arrays)


def _graph_arrays(
    scene: Scene,
    space: GraphSpace,
    s_scale: float,
    d_max: float,
    min_distance: np.ndarray | None,
    edge_feature_names: tuple[str, ...] | list[str],
    vertex_feature_names: tuple[str, ...] | list[str],
    caller: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(x, edge_index, edge_type, edge_attr)`` of a scene, unpadded (``edge_attr`` ``None`` without
    edge features): what :func:`build_observation` pads and :func:`build_graph_batch` wraps.

    :param caller: the public function's name, for the error message
    :raises ValueError: when the names do not match the space's number of edge or node features
    """
    if len(edge_feature_names) != space.edge_features:
        raise ValueError(
            f"{caller}: the space has {space.edge_features} edge features, got names "
            f"{list(edge_feature_names)} (config 'edge_features')"
        )
    if num_node_features(vertex_feature_names) != space.node_features:
        raise ValueError(
            f"{caller}: the space has {space.node_features} node features, the vertex features "
            f"{['s', 'v', 'd', *vertex_feature_names]} give {num_node_features(vertex_feature_names)} "
            f"(config 'vertex_features')"
        )
    x = node_features(
        scene, s_scale=s_scale, d_max=d_max, min_distance=min_distance, vertex_feature_names=vertex_feature_names
    )
    edge_index, edge_type = edges(scene, max_edges=space.max_edges)
    edge_attr = edge_features(scene, edge_index, edge_feature_names, s_scale) if edge_feature_names else None
    return x, edge_index, edge_type, edge_attr


def build_graph_batch(
    scene: Scene,
    space: GraphSpace,
    s_scale: float = DEFAULT_S_SCALE,
    d_max: float = 10.0,
    min_distance: np.ndarray | None = None,
    edge_feature_names: tuple[str, ...] | list[str] = (),
    vertex_feature_names: tuple[str, ...] | list[str] = (),
) -> GraphBatch:
    """The scene as a batch of one graph: what ``sb3_graph.common.batching.padded_to_batch`` makes of
    :func:`build_observation`'s observation, built straight from the scene's arrays.

    Inference on one scene (the GNN planner) then skips the padding to ``max_nodes`` and
    ``max_edges``, the tensor conversion of the padded arrays and their unpadding: at
    intersection sizes those cost more than the graph network itself. The vertices and edges
    come from :func:`node_features` and :func:`edges`, so they cannot point outside the graph.

    :param scene: the vehicles (at most ``space.max_nodes``)
    :param space: the model's ``GraphSpace`` (as for :func:`build_observation`)
    :param s_scale: factor applied to the ``s`` feature (and to the ``distance`` edge feature)
    :param d_max: upper clip of the ``d`` feature
    :param min_distance: precomputed :func:`min_mahalanobis`, optional
    :param edge_feature_names: edge features among :data:`EDGE_FEATURES` (config ``edge_features``)
    :param vertex_feature_names: optional vertex features among :data:`VERTEX_FEATURES` (config ``vertex_features``)
    :return: the batch (CPU tensors; vertex ``i`` is vehicle ``i``, in action slot ``i``)
    :raises ValueError: as :func:`build_observation` for a scene or names that the space cannot hold
    """
    n = scene.num_vehicles
    if n > space.max_nodes:
        raise ValueError(f"build_graph_batch: {n} vertices exceed max_nodes={space.max_nodes}")
    x, edge_index, edge_type, edge_attr = _graph_arrays(
        scene, space, s_scale, d_max, min_distance, edge_feature_names, vertex_feature_names, "build_graph_batch"
    )
    return GraphBatch(
        x=torch.from_numpy(x),
        edge_index=torch.from_numpy(edge_index),
        edge_type=torch.from_numpy(edge_type),
        batch=torch.zeros(n, dtype=torch.long),
        node_slot=torch.arange(n),
        num_graphs=1,
        max_nodes=space.max_nodes,
        edge_attr=None if edge_attr is None else torch.from_numpy(edge_attr),
    )
