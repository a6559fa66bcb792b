"""One junction of a SUMO network read as a layout (``envs.simulation.sumo_junction``)."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

pytest.importorskip("sumolib")

from envs.simulation.layouts import build_layout  # noqa: E402
from envs.simulation.scene import LEFT, MAJOR, MINOR, RIGHT, STRAIGHT  # noqa: E402
from envs.simulation.sumo_junction import NetFileError, read_junction  # noqa: E402
from envs.simulation.sumo_network import write_network  # noqa: E402

CROSS_NODES = """<nodes>
  <node id="C" x="0" y="0" type="priority"/>
  <node id="N" x="0" y="100"/> <node id="S" x="0" y="-100"/> <node id="E" x="100" y="0"/> <node id="W" x="-100" y="0"/>
  {extra_nodes}
</nodes>
"""
CROSS_EDGES = """<edges>
  <edge id="WC" from="W" to="C" priority="3" speed="13.89"/> <edge id="CW" from="C" to="W" priority="3" speed="13.89"/>
  <edge id="EC" from="E" to="C" priority="3" speed="13.89"/> <edge id="CE" from="C" to="E" priority="3" speed="13.89"/>
  <edge id="NC" from="N" to="C" priority="1" speed="13.89"/> <edge id="CN" from="C" to="N" priority="1" speed="13.89"/>
  <edge id="SC" from="S" to="C" priority="1" speed="13.89"/> <edge id="CS" from="C" to="S" priority="1" speed="13.89"/>
  {extra_edges}
</edges>
"""
# A second junction 100 m east of the first: the road goes on from E to a T.
SECOND_JUNCTION = (
    '<node id="F" x="200" y="0"/> <node id="G" x="100" y="100"/>',
    '<edge id="EF" from="E" to="F"/> <edge id="FE" from="F" to="E"/> <edge id="GE" from="G" to="E"/>',
)


def _netconvert(folder, extra=("", "")) -> str:
    """A network that netconvert makes from plain nodes and edges (as from OpenStreetMap, without the download)."""
    import sumolib

    (folder / "x.nod.xml").write_text(CROSS_NODES.format(extra_nodes=extra[0]))
    (folder / "x.edg.xml").write_text(CROSS_EDGES.format(extra_edges=extra[1]))
    out = folder / "x.net.xml"
    cmd = [sumolib.checkBinary("netconvert"), "-n", "x.nod.xml", "-e", "x.edg.xml", "-o", out.name, "--no-turnarounds"]
    subprocess.run(cmd, cwd=folder, check=True, capture_output=True)
    return str(out)


def test_round_trip_of_our_4way_layout(tmp_path):
    """Our 4-way layout -> our generated network -> read back: the same routes, stop lines and exits within 0.1 m,
    the same maneuvers, priorities and conflicts, zones within one sample."""
    ours = build_layout("4way")
    got = read_junction(write_network(ours, tmp_path / "net").net_file)
    assert sorted(got.route_names) == sorted(ours.route_names)
    rows = np.array([got.route_id(name) for name in ours.route_names])
    for arc in ("entry_arc", "exit_arc"):
        mine, theirs = getattr(ours, arc), getattr(got, arc)[rows]
        assert np.abs(mine - theirs).max() < 0.1, arc
        here, there = ours.pose(np.arange(ours.num_routes), mine)[0], got.pose(rows, theirs)[0]
        assert np.abs(here - there).max() < 0.1, arc
    assert np.array_equal(got.maneuver[rows], ours.maneuver)
    assert np.array_equal(got.priority[rows], ours.priority)
    assert np.array_equal(got.conflicts[np.ix_(rows, rows)], ours.conflicts)
    for zone in ("zone_start", "zone_end"):
        gap = (getattr(got, zone)[np.ix_(rows, rows)] - got.entry_arc[rows, None]) - (
            getattr(ours, zone) - ours.entry_arc[:, None]
        )
        assert np.nanmax(np.abs(gap)) <= ours.ds + 1e-9, zone
    # turns keep our speed limits within 15 % (SUMO writes shapes to 0.01 m; the reader smooths them)
    assert np.all(got.speed_limit[rows].min(axis=1) > 0.85 * ours.speed_limit.min(axis=1))


def test_a_netconvert_junction(tmp_path):
    """A four-arm junction that netconvert built: every turn a route, named by compass arm, the major road from
    the higher SUMO priority, maneuvers from SUMO's directions, and crossing paths in conflict."""
    layout = read_junction(_netconvert(tmp_path))
    assert (
        layout.name.endswith("x.net.xml")
        and layout.num_routes == 12
        and set(layout.arms) == {"north", "east", "south", "west"}
    )
    turns = {"east->north": RIGHT, "east->west": STRAIGHT, "east->south": LEFT, "south->east": RIGHT}
    for name, maneuver in turns.items():
        assert layout.maneuver[layout.route_id(name)] == maneuver, name
    assert layout.priority[layout.route_id("west->east")] == MAJOR
    assert layout.priority[layout.route_id("north->south")] == MINOR
    assert layout.conflicts[layout.route_id("west->east"), layout.route_id("north->south")]
    assert not layout.conflicts[layout.route_id("west->east"), layout.route_id("east->west")]
    stop, _ = layout.pose(np.arange(layout.num_routes), layout.entry_arc)
    assert np.all(np.hypot(stop[:, 0], stop[:, 1]) < 15.0)  # stop lines at the junction (centred at the origin)
    assert np.all(layout.exit_arc > layout.entry_arc) and np.all(layout.length > layout.exit_arc)


def test_more_than_one_junction_is_one_line(tmp_path):
    path = _netconvert(tmp_path, SECOND_JUNCTION)
    with pytest.raises(NetFileError, match=r"x\.net\.xml: 2 junctions with connections \((C, E|E, C)\); expected") as e:
        read_junction(path)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "text, message",
    [
        ("<net><edge id='a'", "not a SUMO network"),
        ("not xml at all", "not a SUMO network"),
        ("<net></net>", r"not a SUMO network \(missing attribute 'version'\)"),
        ('<net version="1.20"></net>', "0 junctions with connections"),
        (None, "no such file"),
    ],
)
def test_a_bad_net_file_is_one_line_naming_it(tmp_path, text, message):
    path = tmp_path / "bad.net.xml"
    if text is not None:
        path.write_text(text)
    with pytest.raises(NetFileError, match=message) as e:
        read_junction(path)
    assert str(e.value).startswith(str(path)) and "\n" not in str(e.value)


def test_evaluate_on_a_netconvert_junction_in_both_plants(tmp_path, capsys):
    """``evaluate --net FILE`` runs the planners on the file's junction, in our plant and in SUMO (whose network
    is written from the layout read); without humans both plants give the same figures."""
    import pandas as pd

    from sb3_graph.cli import main

    pytest.importorskip("libsumo")
    net = _netconvert(tmp_path)
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}
    out = tmp_path / "report"
    argv = ["evaluate", "--net", net, "--plant", "builtin", "--plant", "sumo", "--planner", "glide+shield"]
    argv += ["--scenarios", "1", "--duration", "15", "--jobs", "1", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    ours, sumo = (pd.read_csv(out / plant / "metrics.csv") for plant in ("builtin", "sumo"))
    assert (ours["vehicles"] > 0).all() and (ours["crossed"] > 0).all()
    for column in ("crossed", "delay_mean", "collided"):
        assert np.allclose(ours[column], sumo[column], atol=1e-6), column
    assert f'"layout": "net:{net}"' in (out / "sumo" / "scenarios" / "scenario_000.json").read_text()
    # the user's files untouched, nothing written beside them (SUMO's network went into a fresh temporary folder)
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir() if path != out} == before


def test_evaluate_refuses_a_bad_net_in_one_line(tmp_path, capsys):
    from sb3_graph.cli import main

    bad = tmp_path / "mine.net.xml"
    bad.write_text("<net")
    assert main(["evaluate", "--net", str(bad), "--planner", "pr", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sb3-graph evaluate: error: --net: {bad}: not a SUMO network") and err.count("\n") == 1
    assert bad.read_text() == "<net" and not (tmp_path / "out").exists()
