"""A SUMO network generated from a :class:`~envs.simulation.layouts.Layout`, so that both plants drive on
the same geometry.

Plain-XML nodes, edges and connections go through SUMO's ``netconvert``:

- every approach and exit lane of the layout is a one-lane edge whose shape is the lane's centre line
  (``spreadType="center"``), with the layout's priority and speed limit; an exit edge goes on
  :data:`EXIT_EXTENSION` metres past the route's end, so that a vehicle's front can pass it (our plant
  removes a vehicle when its *centre* reaches the end: the SUMO plant removes it there itself);
- the intersection is one priority junction; every route is one connection from its stop line to its exit
  lane whose shape is the route's own polyline between them (sampled every :data:`CONNECTOR_SPACING` m),
  with the lowest speed limit along it (what SUMO's drivers obey; connected vehicles follow the layout's
  limits through our speed governor);
- inD's turn pockets split at a node of their own, which ``netconvert`` smooths over a few metres.

SUMO's frame has ``y`` north: a layout point ``(x, y)`` is ``(x, -y)`` in SUMO. The files are written into a
new folder (a temporary one by default); an existing file is never overwritten.
"""

from __future__ import annotations

import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.simulation.layouts import Layout

# Metres that every exit edge runs on past the end of its route: more than half the longest vehicle a
# scenario may hold (30 m) plus one policy step at the highest speed (100 m/s at 5 Hz), so that no front
# reaches the end of the SUMO route before our plant removes the vehicle (its centre at the route's end).
EXIT_EXTENSION = 40.0
# Spacing of the connection shapes' points [m]: a chord of a 9 m arc this long is 1e-5 m shorter than the arc.
CONNECTOR_SPACING = 0.25
# The junction node: every connection of the layout lies inside it.
JUNCTION = "C"
FILE_NAMES = ("layout.nod.xml", "layout.edg.xml", "layout.con.xml", "layout.net.xml", "netconvert.log")


@dataclass(frozen=True)
class SumoNetwork:
    """The generated network and where each of the layout's routes lies in it.

    :param folder: the folder that holds the files
    :param net_file: the ``.net.xml`` that ``netconvert`` wrote
    :param route_edges: per route, its SUMO edges in driving order (approach edges, then the exit edge)
    :param edge_arcs: per route, the arc along the SUMO route where each of its edges starts [m]
    :param stop_arc: ``(R,)`` the stop line along the SUMO route (end of the last approach edge) [m]
    :param exit_arc: ``(R,)`` the start of the exit edge along the SUMO route [m]
    :param lane_lengths: per route, the SUMO lanes in driving order (internal lanes included) and their lengths
    """

    folder: Path
    net_file: Path
    route_edges: tuple[tuple[str, ...], ...]
    edge_arcs: tuple[np.ndarray, ...]
    stop_arc: np.ndarray
    exit_arc: np.ndarray
    lane_lengths: tuple[tuple[tuple[str, float], ...], ...]


def _edge_id(lane: tuple[str, str, int]) -> str:
    return f"{lane[0]}.{lane[1]}"


def _xy(points: np.ndarray) -> str:
    """Points of the layout's frame as a SUMO shape (``y`` flipped)."""
    return " ".join(f"{x:.4f},{-y:.4f}" for x, y in np.asarray(points, float))


def _network_xml(layout: Layout) -> tuple[str, str, str, tuple[tuple[str, ...], ...]]:
    """The plain-XML nodes, edges and connections of ``layout``, and each route's SUMO edges."""
    net = layout.network
    nodes: dict[str, np.ndarray] = {JUNCTION: np.zeros(2)}
    edges: dict[str, str] = {}
    connections: list[str] = []
    route_edges = []
    for r, lanes in enumerate(layout.route_lanes):
        n_up = int(np.flatnonzero(layout.route_lane_starts[r] == layout.entry_arc[r])[0])
        upstream, exit_lane = lanes[:n_up], lanes[-1]
        for k, key in enumerate(upstream):
            lane = net.get_lane(key)
            shape = _lane_shape(lane)
            to_node = JUNCTION if k == n_up - 1 else key[1]
            nodes.setdefault(key[0], shape[0])
            nodes.setdefault(to_node, shape[-1])
            edges[_edge_id(key)] = _edge_xml(_edge_id(key), key[0], to_node, list(shape), lane)
        lane = net.get_lane(exit_lane)
        shape = _lane_shape(lane)
        direction = (shape[-1] - shape[-2]) / np.linalg.norm(shape[-1] - shape[-2])
        far = shape[-1] + EXIT_EXTENSION * direction  # on the line of the last piece: that piece's end drops out
        nodes.setdefault(exit_lane[1], far)
        edges[_edge_id(exit_lane)] = _edge_xml(_edge_id(exit_lane), JUNCTION, exit_lane[1], [*shape[:-1], far], lane)
        a0, a1 = layout.entry_arc[r], layout.exit_arc[r]
        arcs = np.append(np.arange(a0, a1, CONNECTOR_SPACING), a1)
        shape, _ = layout.pose(np.full(arcs.size, r), arcs)
        k0, k1 = int(a0 / layout.ds), int(a1 / layout.ds) + 1
        speed = float(layout.speed_limit[r, k0:k1].min())
        connections.append(
            f'  <connection from="{_edge_id(upstream[-1])}" to="{_edge_id(exit_lane)}" fromLane="0" toLane="0" '
            f'speed="{speed:.4f}" shape="{_xy(shape)}"/>'
        )
        route_edges.append(tuple(_edge_id(key) for key in upstream) + (_edge_id(exit_lane),))
    node_xml = "\n".join(
        f'  <node id="{name}" x="{p[0]:.4f}" y="{-p[1]:.4f}" type="priority"/>' for name, p in nodes.items()
    )
    return (
        f"<nodes>\n{node_xml}\n</nodes>\n",
        "<edges>\n" + "\n".join(edges.values()) + "\n</edges>\n",
        "<connections>\n" + "\n".join(connections) + "\n</connections>\n",
        tuple(route_edges),
    )


def _lane_shape(lane) -> np.ndarray:
    """A lane's centre line as points: its own (a lane read from a SUMO network), or a straight lane's two ends."""
    points = getattr(lane, "points", None)
    if points is not None:
        return np.asarray(points, float)
    return np.array([lane.position(0.0, 0.0), lane.position(lane.length, 0.0)])


def _edge_xml(edge_id: str, from_node: str, to_node: str, shape: list, lane) -> str:
    return (
        f'  <edge id="{edge_id}" from="{from_node}" to="{to_node}" priority="{int(lane.priority)}" numLanes="1" '
        f'speed="{float(lane.speed_limit):.4f}" width="{float(lane.width):.4f}" spreadType="center" '
        f'shape="{_xy(shape)}"/>'
    )


def _fresh_folder(folder: str | Path | None) -> Path:
    """A new temporary folder, or ``folder`` (created if missing) when it holds none of our file names."""
    if folder is None:
        return Path(tempfile.mkdtemp(prefix="sb3-graph-sumo-"))
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    taken = [name for name in FILE_NAMES if (folder / name).exists()]
    if taken:
        raise ValueError(f"{folder / taken[0]}: exists already; the SUMO network goes into a folder without it")
    return folder


def write_network(layout: Layout, folder: str | Path | None = None, netconvert: str | None = None) -> SumoNetwork:
    """Generate the SUMO network of ``layout`` with ``netconvert``.

    :param layout: the intersection
    :param folder: where the files go (created if missing; default: a new temporary folder); a file of the
        same name already there is an error, never overwritten
    :param netconvert: the ``netconvert`` binary (default: the one of the ``eclipse-sumo`` package)
    :return: the network and where the routes lie in it
    :raises ValueError: when a file exists already, or ``netconvert`` fails (naming its log)
    """
    import sumolib  # the sumo extra; the caller (SumoPlant) has checked that it is installed

    out = _fresh_folder(folder)
    nodes, edges, connections, route_edges = _network_xml(layout)
    paths = [out / name for name in FILE_NAMES]
    for path, text in zip(paths, (nodes, edges, connections)):
        with open(path, "x", encoding="utf-8") as fh:  # "x": never over a file that appeared meanwhile
            fh.write(text)
    binary = netconvert or sumolib.checkBinary("netconvert")
    cmd = [binary, "-n", paths[0], "-e", paths[1], "-x", paths[2], "-o", paths[3]]
    cmd += ["--offset.disable-normalization", "--no-turnarounds", "--no-warnings"]
    done = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, check=False)
    with open(paths[4], "x", encoding="utf-8") as fh:
        fh.write(done.stdout + done.stderr)
    if done.returncode != 0 or not paths[3].exists():
        raise ValueError(f"netconvert failed on the {layout.name} layout (exit {done.returncode}); see {paths[4]}")
    return _read_routes(paths[3], out, route_edges)


def _read_routes(net_file: Path, folder: Path, route_edges: tuple[tuple[str, ...], ...]) -> SumoNetwork:
    """Walk every route's lanes in the written network (internal lanes included) for its arcs."""
    import sumolib

    net = sumolib.net.readNet(str(net_file), withInternal=True)
    edge_arcs, stop, exit_, lanes_out = [], [], [], []
    for edges in route_edges:
        lanes: list[tuple[str, float]] = []
        edge_start = []
        arc = 0.0
        for e0, e1 in zip(edges[:-1], edges[1:]):
            lane = net.getEdge(e0).getLane(0)
            edge_start.append(arc)
            lanes.append((lane.getID(), lane.getLength()))
            arc += lane.getLength()
            stop_here = arc  # the last approach edge's end is the stop line
            link = next(c for c in lane.getOutgoing() if c.getToLane().getEdge().getID() == e1)
            via = link.getViaLaneID()
            while via:  # internal lanes, split where a left turn waits inside the junction
                length = net.getLane(via).getLength()
                lanes.append((via, length))
                arc += length
                following = net.getLane(via).getOutgoing()
                via = following[0].getViaLaneID() if following else ""
        stop.append(stop_here)
        exit_.append(arc)
        edge_start.append(arc)
        edge_arcs.append(np.asarray(edge_start))
        last = net.getEdge(edges[-1]).getLane(0)
        lanes.append((last.getID(), last.getLength()))
        lanes_out.append(tuple(lanes))
    return SumoNetwork(
        folder=folder, net_file=net_file, route_edges=route_edges, edge_arcs=tuple(edge_arcs),
        stop_arc=np.asarray(stop), exit_arc=np.asarray(exit_), lane_lengths=tuple(lanes_out),
    )  # fmt: skip
