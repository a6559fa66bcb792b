"""Mapping recorded tracks to arms, maneuvers and layout routes, from the tracks alone."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from envs.ind import mapping as m
from envs.ind.loader import load_recording, load_recordings
from envs.ind.synthetic import (
    ARMS,
    SyntheticSite,
    SyntheticVehicle,
    default_vehicles,
    make_recording,
    maneuver_of,
    write_recording,
)

SITE = SyntheticSite(centre=(-312.5, 87.25), rotation_deg=23.0)
LABELS = {  # synthetic reason labels -> mapping reasons
    "parked": m.REASON_PARKED,
    "u-turn": m.REASON_U_TURN,
    "starts inside": m.REASON_STARTS_INSIDE,
    "ends inside": m.REASON_ENDS_INSIDE,
    "off arm": m.REASON_ENTRY_OFF_ARM,
}


def _write(folder, recording_id, site, seed=0, num=36):
    recording = make_recording(recording_id, default_vehicles(seed=seed, num=num), site)
    write_recording(folder, recording)
    return recording


@pytest.fixture(scope="module")
def site_a(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ind")
    written = _write(folder, 7, SITE)
    return written, m.map_recordings([load_recording(folder, 7)])


def test_every_track_has_a_row_and_unmapped_ones_a_reason(site_a):
    written, mapped = site_a
    table = mapped.tracks.set_index("track_id")
    assert sorted(table.index) == sorted(written.tracks_meta["trackId"])
    assert (table.loc[table["mapped"], "reason"] == "").all()
    assert (table.loc[~table["mapped"], "reason"] != "").all()
    expected = written.expected
    for track_id, label in expected["reason"].items():
        if label == "not modelled":
            assert table.loc[track_id, "reason"] == f"not modelled: {expected.loc[track_id, 'class']}"
        elif label:
            assert table.loc[track_id, "reason"] == LABELS[label], track_id
        else:
            assert table.loc[track_id, "mapped"], track_id


def test_maneuvers_arms_times_and_speeds(site_a):
    written, mapped = site_a
    table = mapped.mapped.set_index("track_id")
    expected = written.expected.loc[table.index]
    assert len(table) == (written.expected["reason"] == "").sum() > 30
    assert (table["maneuver"] == expected["maneuver"]).all()
    # Rotated by 23 degrees, the arms still carry their compass names.
    assert (table["entry_arm"] == expected["entry"]).all()
    assert (table["exit_arm"] == expected["exit"]).all()
    np.testing.assert_allclose(table["time"], expected["time"])
    np.testing.assert_allclose(table["speed"], expected["speed"], atol=0.01)
    assert (table["stopped"] == expected["stopped"]).all()
    # Every mapped vehicle passes the centre between its first and last frame, inside the intersection.
    assert ((table["t_centre"] > table["time"]) & (table["t_centre"] < table["t_last"])).all()
    assert (table["min_distance"] < mapped.options.inner_radius).all()
    assert set(table["maneuver"]) == {"left", "straight", "right"}


def test_centre_and_arms_are_found_at_a_shifted_rotated_site(site_a):
    _, mapped = site_a
    assert mapped.centre_estimated
    assert np.hypot(*(mapped.centre - np.array(SITE.centre))) < 2.5
    assert list(mapped.arms.index) == ["east", "north", "west", "south"]
    true_angles = SITE.rotation_deg + 90.0 * np.arange(4)
    assert np.abs(m._wrap_deg(mapped.arms["angle_deg"].to_numpy() - true_angles)).max() < 5.0
    # Busiest road (east-west in the synthetic traffic) is the major road.
    assert set(mapped.arms.index[mapped.arms["major"]]) == {"east", "west"}
    table = mapped.mapped
    assert (table["priority"] == np.where(table["entry_arm"].isin(["east", "west"]), "major", "minor")).all()


def test_given_centre_is_used(tmp_path):
    _write(tmp_path, 7, SITE, num=12)
    options = m.MappingOptions(centre=SITE.centre)
    mapped = m.map_recordings([load_recording(tmp_path, 7)], options)
    assert not mapped.centre_estimated
    np.testing.assert_array_equal(mapped.centre, SITE.centre)
    assert mapped.mapped["maneuver"].isin(["left", "straight", "right"]).all()


@pytest.mark.parametrize("rotation", [-100.0, 68.0, 151.0])
def test_maneuvers_do_not_depend_on_the_site_orientation(tmp_path, rotation):
    site = SyntheticSite(centre=(1234.0, -987.0), rotation_deg=rotation, location_id=2)
    written = _write(tmp_path, 20, site, seed=3, num=24)
    mapped = m.map_recordings([load_recording(tmp_path, 20)])
    table = mapped.mapped.set_index("track_id")
    expected = written.expected.loc[table.index]
    assert len(table) == (written.expected["reason"] == "").sum()
    assert (table["maneuver"] == expected["maneuver"]).all()
    # The recorded arm names are a rotation of the synthetic ones: one name per synthetic arm.
    pairs = pd.concat([expected["entry"], table["entry_arm"]], axis=1).drop_duplicates()
    assert len(pairs) == 4 and pairs.iloc[:, 0].is_unique and pairs.iloc[:, 1].is_unique
    shift = {(ARMS.index(a) - m.COMPASS.index(b)) % 4 for a, b in pairs.itertuples(index=False)}
    assert len(shift) == 1


def test_major_road_override_and_layout_alignment(tmp_path):
    _write(tmp_path, 7, SITE)
    recording = load_recording(tmp_path, 7)
    mapped = m.map_recordings([recording], m.MappingOptions(major_arms=("north", "south")))
    assert set(mapped.arms.index[mapped.arms["major"]]) == {"north", "south"}
    # The layout's major road is east-west, so the recorded north-south road is turned onto it.
    assert {mapped.arms.loc["north", "layout_arm"], mapped.arms.loc["south", "layout_arm"]} == {
        "east",
        "west",
    }
    table = mapped.mapped
    layout_maneuver = [maneuver_of(*route.split("->")) for route in table["route"]]
    assert (np.array(layout_maneuver) == table["maneuver"].to_numpy()).all()
    assert (
        table["priority"] == np.where(table["entry_arm"].isin(["north", "south"]), "major", "minor")
    ).all()
    with pytest.raises(ValueError, match="major_arms.*not arms"):
        m.map_recordings([recording], m.MappingOptions(major_arms=("north", "up")))


def test_align_arms_keeps_rotation_sense_and_major_road():
    recorded = {"a": 10.0, "b": 100.0, "c": 190.0, "d": 280.0}
    layout = m.LayoutArms(
        angles={n: k * np.pi / 2 for k, n in enumerate(m.COMPASS)}, major=("north", "south")
    )
    pairing = m.align_arms(recorded, ("a", "c"), layout)
    assert {pairing["a"], pairing["c"]} == {"north", "south"}
    # Counter-clockwise order is kept: each recorded arm's ccw neighbour maps to the layout neighbour.
    order = ["a", "b", "c", "d"]
    for k, arm in enumerate(order):
        nxt = order[(k + 1) % 4]
        assert m.COMPASS.index(pairing[nxt]) == (m.COMPASS.index(pairing[arm]) + 1) % 4
    # With a matching major road the least rotation wins: a ~ east.
    same = m.align_arms(recorded, ("a", "c"), m.DEFAULT_LAYOUT)
    assert same == {"a": "east", "b": "north", "c": "west", "d": "south"}
    with pytest.raises(ValueError, match="no rotation"):
        m.align_arms(recorded, ("a", "b"), m.DEFAULT_LAYOUT)
    with pytest.raises(ValueError, match="3 arms"):
        m.align_arms({"a": 0.0, "b": 120.0, "c": 240.0}, ("a", "b"), m.DEFAULT_LAYOUT)
    with pytest.raises(ValueError, match="major"):
        m.LayoutArms(angles={"x": 0.0, "y": 1.0}, major=("x", "z"))


def test_find_arms_and_compass_names():
    rng = np.random.default_rng(0)
    true = np.array([5.0, 97.0, 181.0, 268.0])
    angles = np.concatenate([t + rng.normal(0, 4, 50) for t in true] + [np.array([50.0, 140.0])])
    arms = m.find_arms(angles, 4)
    assert np.abs(m._wrap_deg(arms - true)).max() < 2.0
    assert m.compass_names(arms) == ["east", "north", "west", "south"]
    assert m.compass_names(np.array([50.0, 140.0, 230.0, 320.0]))[0] in ("east", "north")
    with pytest.raises(ValueError, match="approach arms"):
        m.find_arms(np.array([0.0, 1.0, 180.0]), 4)


def test_estimate_centre_and_its_errors():
    centre = np.array([12.0, -7.0])
    angles = np.deg2rad([0.0, 90.0, 180.0, 270.0, 45.0])
    directions = np.column_stack([np.cos(angles), np.sin(angles)])
    points = centre + 30.0 * directions
    np.testing.assert_allclose(m.estimate_centre(points, directions), centre, atol=1e-9)
    with pytest.raises(ValueError, match="parallel"):
        m.estimate_centre(points[:2] * 0 + [[0.0, 0.0], [0.0, 5.0]], np.array([[1.0, 0.0], [1.0, 0.0]]))


def test_options_are_validated():
    with pytest.raises(ValueError, match="inner_radius"):
        m.MappingOptions(inner_radius=-1.0)
    with pytest.raises(ValueError, match="num_arms"):
        m.MappingOptions(num_arms=2)
    with pytest.raises(ValueError, match="centre"):
        m.MappingOptions(centre=(1.0, float("nan")))
    with pytest.raises(ValueError, match="major_arms"):
        m.MappingOptions(major_arms=("east", "east"))


def test_recordings_of_one_site_are_mapped_together_with_their_own_times(tmp_path):
    a = _write(tmp_path, 7, SITE, seed=0, num=16)
    b = _write(tmp_path, 8, SITE, seed=5, num=16)
    recordings = load_recordings(tmp_path, [7, 8])
    # Without the arrival timing, vehicles appear at their recorded appearance times.
    mapped = m.map_recordings(recordings, m.MappingOptions(arrival_timing=False))
    assert mapped.tracks["t_entry"].isna().all()
    assert sorted(mapped.tracks["recording"].unique()) == [7, 8]
    records = m.scenario_records(mapped)
    assert list(records.columns[:4]) == ["time", "route", "speed", "vehicle_id"]
    for rid, written in ((7, a), (8, b)):
        part = records[records["recording"] == rid]
        assert part["time"].is_monotonic_increasing
        expected = written.expected[written.expected["reason"] == ""]
        assert sorted(part["vehicle_id"]) == sorted(expected.index)
        np.testing.assert_allclose(
            part.set_index("vehicle_id")["time"].sort_index(), expected["time"].sort_index()
        )
    assert records["route"].str.fullmatch(r"(east|north|west|south)->(east|north|west|south)").all()
    assert len(m.scenario_records(mapped, recording=8)) == (b.expected["reason"] == "").sum()
    # With it (the default), every recording is timed from its own frames: same vehicles, other times.
    timed = m.scenario_records(m.map_recordings(recordings))
    assert (timed.groupby("recording").size() == records.groupby("recording").size()).all()
    merged = timed.merge(records, on=["recording", "vehicle_id"], suffixes=("", "_raw"))
    assert len(merged) == len(records) and (merged["time"] != merged["time_raw"]).any()


def test_routes_and_maneuvers_agree_with_the_simulated_ind_layout(site_a, tmp_path):
    layouts = pytest.importorskip("envs.simulation.layouts")
    layout = layouts.build_layout("inD")
    arms = m.layout_arms(layout)
    assert arms.angles["north"] == pytest.approx(np.pi / 2)  # y flipped into the inD frame
    assert set(arms.major) == {"east", "west"}
    written, _ = site_a
    write_recording(tmp_path, written)
    # Declare the recorded north-south road major, so that the alignment has to turn the arms.
    options = m.MappingOptions(major_arms=("north", "south"))
    table = m.map_recordings([load_recording(tmp_path, 7)], options, arms).mapped
    route_ids = np.array([layout.route_id(r) for r in table["route"]])
    codes = {name: k for k, name in enumerate(("left", "straight", "right"))}
    np.testing.assert_array_equal(layout.maneuver[route_ids], table["maneuver"].map(codes).to_numpy())
    # The recorded major road enters on the layout's major-road routes.
    np.testing.assert_array_equal(layout.priority[route_ids] == 1, (table["priority"] == "major").to_numpy())


def test_short_minor_arms_with_wide_lanes_are_still_one_arm_each(tmp_path):
    # The real site shows the minor road only a short way: its two lanes lie far apart in angle.
    site = SyntheticSite(
        centre=(10.0, -500.0), rotation_deg=-20.0, arm_lengths=(50.0, 13.0, 50.0, 13.0), lane_offset=3.0
    )
    written = _write(tmp_path, 7, site, seed=2, num=40)
    mapped = m.map_recordings([load_recording(tmp_path, 7)])
    table = mapped.tracks.set_index("track_id")
    expected = written.expected.loc[table.index]
    assert ((table["reason"] == "") == (expected["reason"] == "")).all()
    assert (table.loc[table["mapped"], "maneuver"] == expected.loc[table["mapped"], "maneuver"]).all()
    assert len(mapped.arms) == 4
    assert np.abs(np.diff(np.sort(mapped.arms["angle_deg"].to_numpy()))).min() > 60.0


def test_a_vehicle_without_frames_is_listed_not_mapped(tmp_path):
    written = _write(tmp_path, 7, SITE, num=12)
    path = tmp_path / "07_tracks.csv"
    tracks = pd.read_csv(path)
    tracks[tracks["trackId"] != 2].to_csv(path, index=False)
    table = m.map_recordings([load_recording(tmp_path, 7)]).tracks.set_index("track_id")
    assert not table.loc[2, "mapped"] and table.loc[2, "reason"] == m.REASON_NO_FRAMES
    assert table["mapped"].sum() == (written.expected["reason"] == "").sum() - 1


def test_too_few_moving_vehicles_is_an_error(tmp_path):
    write_recording(
        tmp_path, make_recording(7, [SyntheticVehicle("east", "west", 0.0, 8.0)], SITE, extras=False)
    )
    with pytest.raises(ValueError, match="nothing to map"):
        m.map_recordings([load_recording(tmp_path, 7)])


# Arms seen out to very different distances, as at the real site (east, north, west, south).
UNEVEN = SyntheticSite(centre=(40.0, -25.0), rotation_deg=8.0, arm_lengths=(75.0, 22.0, 55.0, 30.0))


def _uneven(tmp_path, vehicles=None):
    vehicles = vehicles or default_vehicles(seed=4, num=30)
    written = make_recording(7, [SyntheticVehicle(v.entry, v.exit, v.time, v.speed) for v in vehicles], UNEVEN)
    write_recording(tmp_path, written)  # no stops: every vehicle keeps its speed up to the stop line
    return written, load_recording(tmp_path, 7)


def test_arrival_timing_reaches_the_stop_line_when_the_recorded_vehicle_entered(tmp_path):
    from envs.simulation.layouts import build_layout

    written, recording = _uneven(tmp_path)
    routes = m.layout_arms(build_layout("inD")).routes
    # The true centre (an estimate is off by up to a metre), so that the reference below is exact.
    table = m.map_recordings([recording], m.MappingOptions(centre=UNEVEN.centre)).mapped.set_index("track_id")
    expected = written.expected.loc[table.index]
    geometry = routes.loc[table["route"]]
    radius = geometry["entry_radius"].to_numpy()
    # Reference from the synthetic geometry: a vehicle at constant speed on its incoming lane (lane_offset
    # beside the arm's axis) comes within `radius` of the centre after arm length - sqrt(r^2 - offset^2).
    arm_length = np.array([UNEVEN.length_of(a) for a in expected["entry"]])
    to_entry = arm_length - np.sqrt(radius**2 - UNEVEN.lane_offset**2)
    t_entry = expected["time"].to_numpy() + to_entry / expected["speed"].to_numpy()
    np.testing.assert_allclose(table["t_entry"], t_entry, atol=0.1)  # frames 0.04 s, path points 0.25 m
    # A simulated vehicle appears with its rear at the route's start and drives at the recorded speed
    # clipped to the limit: its centre reaches the stop line at the recorded entry time (or later when
    # that would need an appearance before time 0).
    speed = np.clip(table["speed"].to_numpy(), 3.0, geometry["speed_limit"].to_numpy())
    arrival = table["spawn_time"] + (geometry["entry_arc"].to_numpy() - table["length"].to_numpy() / 2) / speed
    positive = table["spawn_time"] > 0
    np.testing.assert_allclose(arrival[positive], table.loc[positive, "t_entry"], atol=1e-9)
    assert (table["spawn_time"] >= 0).all() and (arrival[~positive] >= table.loc[~positive, "t_entry"]).all()
    # Appearing at the recorded appearance time instead would shift arrivals by arm: the short north arm's
    # vehicles would arrive several seconds late, the long east arm's much less.
    late = pd.Series(
        (table["time"] + (arrival - table["spawn_time"]) - table["t_entry"]).to_numpy(), index=table["entry_arm"]
    )
    by_arm = late.groupby(level=0).mean()
    assert by_arm["north"] - by_arm["east"] > 3.0


def test_arrival_timing_is_never_before_time_zero_and_falls_back_to_the_centre(tmp_path):
    from envs.simulation.layouts import build_layout

    vehicles = [
        SyntheticVehicle("north", "south", 0.5, 8.0),  # short arm: would have to appear before 0
        SyntheticVehicle("east", "west", 10.0, 8.0),
        SyntheticVehicle("west", "north", 15.0, 7.0),
        SyntheticVehicle("south", "east", 25.0, 9.0),
        SyntheticVehicle("west", "east", 40.0, 0.5),  # crawls in: timed with min_timing_speed
    ]
    written, recording = _uneven(tmp_path, vehicles)
    table = m.map_recordings([recording]).mapped.set_index("track_id")
    assert table.loc[0, "spawn_time"] == 0.0 and (table["spawn_time"].iloc[1:] > 0).all()
    routes = m.layout_arms(build_layout("inD"))
    floor = m.MappingOptions().min_timing_speed
    travel = routes.routes.loc[table.loc[4, "route"], "entry_arc"] - table.loc[4, "length"] / 2
    assert table.loc[4, "spawn_time"] == pytest.approx(table.loc[4, "t_entry"] - travel / floor)
    # A radius no track comes within: closest approach minus the layout's travel from stop line to it.
    tight = m.map_recordings([recording], m.MappingOptions(entry_radius=0.5)).mapped.set_index("track_id")
    assert (tight["min_distance"] >= 0.5).all()
    inside = routes.routes.loc[tight["route"], "inside"].to_numpy()
    speed = np.clip(tight["speed"].to_numpy(), floor, 10.0)
    np.testing.assert_allclose(tight["t_entry"], tight["t_centre"] - inside / speed)


def test_arrival_timing_options_and_errors(tmp_path):
    _, recording = _uneven(tmp_path)
    with pytest.raises(ValueError, match="entry_radius"):
        m.MappingOptions(entry_radius=-2.0)
    with pytest.raises(ValueError, match="min_timing_speed"):
        m.MappingOptions(min_timing_speed=0.0)
    with pytest.raises(ValueError, match="arrival_timing"):
        m.map_recordings([recording], layout=m.DEFAULT_LAYOUT)  # no route geometry to time with
    raw = m.map_recordings([recording], m.MappingOptions(arrival_timing=False), m.DEFAULT_LAYOUT).mapped
    np.testing.assert_array_equal(raw["spawn_time"], raw["time"])
