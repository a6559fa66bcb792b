"""``lookahead`` beside the steps and over the cores: its search process and its pool of rollout helpers."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from lookahead_support import busy_scene, drive

import envs  # noqa: F401  (registers the environments)
from envs.evaluation.harness import evaluation_env_kwargs
from envs.planners.glide import RECIPE
from envs.planners.lookahead import LookaheadParams, LookaheadPlanner
from envs.planners.search_workers import available_cores
from envs.planners.shield import Shield
from envs.simulation.traffic import generate_scenario

two_cores = pytest.mark.skipif(available_cores() < 2, reason="needs 2 cores")


class OnTime(Shield):
    """Before a step, waits for the search due by then: a clock on which no search is late."""

    def act(self, scene):
        planner = self.planner
        inflight = getattr(planner, "_inflight", None)
        if inflight is not None and not inflight["done"] and planner._steps >= inflight["due"]:
            planner._process.conn.poll(60)
        return super().act(scene)


@pytest.mark.parametrize("value", [0, available_cores() + 1, 1.5, True, "2"])
def test_a_worker_count_out_of_range_names_the_parameter_and_the_range(value):
    with pytest.raises(ValueError, match=f"^lookahead's workers must be an integer from 1 to {available_cores()}"):
        LookaheadParams(workers=value)


@pytest.mark.parametrize(
    "field, value", [("mode", "delayed"), ("clock", "cpu"), ("latency", 0.0), ("latency", float("inf"))]
)
def test_a_bad_mode_or_latency_names_it_in_one_line(field, value):
    with pytest.raises(ValueError, match=f"^lookahead's {field} must be") as error:
        LookaheadParams(**{field: value})
    assert "\n" not in str(error.value)


def test_the_default_workers_are_the_cores_but_one_on_the_wall_clock_and_one_in_simulated_time():
    assert LookaheadParams().processes == 1
    assert LookaheadParams(mode="async").processes == 1
    assert LookaheadParams(mode="async", clock="wall").processes == max(1, available_cores() - 1)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_the_search_process_runs_lower_than_the_steps():
    """The search process lowers its own priority (checked in a child); the process that steps keeps its own."""
    from envs.planners.search_workers import NICENESS, lower_priority

    read, write = os.pipe()
    before = os.nice(0)
    pid = os.fork()
    if pid == 0:  # the child: lower itself, report its niceness
        os.close(read)
        os.write(write, f"{lower_priority()} {os.nice(0)}".encode())
        os._exit(0)
    os.close(write)
    lowered, nice = os.read(read, 100).decode().split()
    os.close(read)
    os.waitpid(pid, 0)
    assert lowered == "True" and int(nice) == min(19, before + NICENESS) and os.nice(0) == before


@two_cores
def test_rollouts_over_two_workers_choose_bit_for_bit_as_one():
    """The exact bound shared between the workers only stops rollouts that cannot win: the same commands."""
    one = LookaheadPlanner()
    want = drive(Shield(one), seconds=15.0, seed=3)
    two = LookaheadPlanner(params=LookaheadParams(workers=2))
    got = drive(Shield(two), seconds=15.0, seed=3)
    two.close()
    assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
    assert two.searches == one.searches > 10 and two.fallbacks == 0 and two.worker_restarts == 0


def test_an_async_search_in_simulated_time_lands_exactly_its_latency_later(monkeypatch):
    """Its windows apply from the step ``latency`` after the search starts, glide's own until then; the next
    search starts one period after the last."""
    planted = np.full(4, 7.0)

    def search_ahead(self, scene, road_windows, proposed, steps):
        return scene.time + steps * scene.dt, planted

    monkeypatch.setattr(LookaheadPlanner, "search_ahead", search_ahead)
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", latency=0.6))
    planner.reset(0)
    scene = busy_scene()
    windows = [planner.windows_for(scene)[0] for _ in range(8)]
    assert windows == [RECIPE.window] * 3 + [7.0] * 5
    stats = planner.stats()
    assert stats["lookahead_started"] == 2 and stats["lookahead_applied"] == 1 and stats["lookahead_late"] == 0


def test_windows_older_than_the_horizon_give_way_to_glides_own(monkeypatch):
    """Searches that land 3 s after they start, with a 1 s horizon: between two answers, the windows expire once
    they are more than a horizon old, and glide's own window holds until the next answer."""
    planted = np.full(4, 7.0)

    def search_ahead(self, scene, road_windows, proposed, steps):
        return scene.time + steps * scene.dt, planted

    monkeypatch.setattr(LookaheadPlanner, "search_ahead", search_ahead)
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", latency=3.0, horizon=1.0))
    planner.reset(0)
    scene = busy_scene()
    windows = []
    for k in range(31):
        windows.append(planner.windows_for(replace(scene, time=scene.time + k * scene.dt))[0])
    # lands at step 15 (age 0), expires at step 21 (age 1.2 s > 1 s), the next lands at step 30
    assert windows == [RECIPE.window] * 15 + [7.0] * 6 + [RECIPE.window] * 9 + [7.0]
    assert planner.stats()["lookahead_expired"] == 1 and planner.applied == 2


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=two_cores)])
def test_the_search_process_drives_as_its_deterministic_emulation_when_on_time(workers):
    """A search in its own process (the ``"wall"`` clock), with no search late, gives the commands of its emulation
    in simulated time bit for bit (at the same latency: left free, the process's follows the wall time of its
    searches)."""
    delayed = LookaheadPlanner(params=LookaheadParams(mode="async"))
    want = drive(Shield(delayed), seconds=15.0, seed=3)
    beside = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=workers, latency=1.0))
    got = drive(OnTime(beside), seconds=15.0, seed=3)
    beside.close()
    assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
    stats = beside.stats()
    assert stats["lookahead_applied"] == delayed.applied > 10
    assert stats["lookahead_late"] == stats["lookahead_dropped"] == stats["lookahead_worker_restarts"] == 0


def slow(seconds: float):
    """A ``search_ahead`` that takes ``seconds`` first (patched before the search process forks)."""
    real = LookaheadPlanner.search_ahead

    def search_ahead(self, *args):
        time.sleep(seconds)
        return real(self, *args)

    return search_ahead


def test_the_latency_of_the_search_process_follows_the_wall_time_of_its_searches(monkeypatch):
    """Left free, an ``"async"`` search is predicted as far ahead as the last searches took (in steps of the wall
    time between steps), so that it lands on time."""
    monkeypatch.setattr(LookaheadPlanner, "search_ahead", slow(0.5))
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=1))
    planner.reset(0)
    scene = busy_scene()
    tic = time.perf_counter()
    while planner.started < 3 and time.perf_counter() - tic < 30:
        planner.windows_for(scene)
        time.sleep(0.05)
    planner.close()
    # the first search: one period ahead (5 steps); the next ones: at least 0.5 s in steps of about 0.05 s
    assert planner.stats()["lookahead_ahead_s"] > (1.0 + 2 * 8 * 0.2) / 3


@pytest.mark.parametrize("sleep, pause, applied", [(0.6, 0.05, True), (1.5, 0.005, False)])
def test_a_slow_search_never_blocks_a_step_and_is_counted_late(monkeypatch, sleep, pause, applied):
    """A late answer is applied (it is still the newest) unless it is a horizon late (40 steps): then dropped."""
    monkeypatch.setattr(LookaheadPlanner, "search_ahead", slow(sleep))
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=1, latency=0.2))
    planner.reset(0)
    scene = busy_scene()
    planner.windows_for(scene)  # starts the process and the first search
    worst, tic = 0.0, time.perf_counter()
    while planner.stats()["lookahead_late"] == 0 and time.perf_counter() - tic < 30:
        step = time.perf_counter()
        planner.act(scene)
        worst = max(worst, time.perf_counter() - step)
        time.sleep(pause)
    planner.close()
    assert planner.late == 1 and planner.started == 2  # the next search started as soon as the late one came
    assert worst < 0.3  # the steps went on while the search slept
    assert (planner.applied, planner.dropped) == ((1, 0) if applied else (0, 1))


def die_once(flag):
    """A ``search_ahead`` whose first call, in the search process, ends that process."""
    real = LookaheadPlanner.search_ahead

    def search_ahead(self, *args):
        if not flag.exists():
            flag.touch()
            os._exit(3)
        return real(self, *args)

    return search_ahead


def test_a_search_process_that_dies_is_replaced_and_the_step_answers_from_glides_windows(monkeypatch, tmp_path):
    monkeypatch.setattr(LookaheadPlanner, "search_ahead", die_once(tmp_path / "died"))
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=1))
    planner.reset(0)
    scene = busy_scene()
    planner._road_windows = np.full(4, 30.0)  # a search's windows in force
    tic = time.perf_counter()
    while planner.worker_restarts == 0 and time.perf_counter() - tic < 30:
        planner.act(scene)
        time.sleep(0.02)
    assert planner.worker_restarts == 1 and planner.dropped == 1
    assert np.all(planner.windows_for(scene) == RECIPE.window)  # glide's own until a fresh process answers
    while planner.applied == 0 and time.perf_counter() - tic < 60:
        planner.act(scene)
        time.sleep(0.02)
    planner.close()
    assert planner.applied >= 1 and planner.worker_restarts == 1  # the fresh process answered


@two_cores
def test_a_rollout_helper_that_dies_voids_its_search_and_is_replaced(monkeypatch):
    parent = os.getpid()
    real = LookaheadPlanner.rollout

    def rollout(self, *args, **kwargs):
        if os.getpid() != parent:
            os._exit(3)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(LookaheadPlanner, "rollout", rollout)
    planner = LookaheadPlanner(params=LookaheadParams(workers=2))
    planner.reset(0)
    scene = busy_scene()
    assert planner._search(scene) is None  # glide's own window for this period
    assert planner.worker_restarts == 1 and planner.fallbacks == 1
    assert planner._pool.alive()
    planner.close()


def test_an_answer_for_another_episode_is_dropped_and_counted():
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=1))
    planner.reset(0)
    scene = busy_scene()
    planner.windows_for(scene)  # a search starts
    planner.reset(1)  # a new episode before it answers
    tic = time.perf_counter()
    while planner.mismatched == 0 and time.perf_counter() - tic < 30:
        planner.windows_for(scene)
        time.sleep(0.02)
    planner.close()
    assert planner.mismatched == 1 and planner.applied == 0


def test_the_server_serves_lookahead_beside_the_steps_and_reports_its_searches():
    """``serve --planner lookahead --shield``: the stream's search runs beside its steps, and each JSON answer
    reports the searches (started, applied, late, dropped ...)."""
    pytest.importorskip("fastapi")
    import json

    from envs.serve.app import PlannerService
    from envs.serve.schema import OpenRequest, StepReply
    from envs.serve.wire import scene_to_wire

    service = PlannerService("lookahead", "CoopIntersection4Way-v0", shield=True)
    assert service.prototype.planner.search.mode == "async" and service.prototype.planner.search.clock == "wall"
    stream = service.open(OpenRequest(layout="4way", seed=0))
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    env.reset(seed=3, options={"scenario": generate_scenario("4way", 60.0, 3, rate_range=(0.4, 0.4))})
    for seq in range(1, 281):  # 60 steps, more while the first search has not answered (a loaded machine)
        body = json.dumps({**scene_to_wire(env.unwrapped.scene()), "seq": seq}).encode()
        status, answer = service.handle("step", stream.id, body)
        assert status == 200
        reply = StepReply.model_validate_json(answer)
        env.step(env.unwrapped.accelerations_to_action(np.array(reply.accelerations)))
        time.sleep(0.02)
        if seq >= 60 and reply.search.started >= 2:
            break
    stream.planner.planner.close()
    assert reply.search is not None and reply.search.started >= 2
    assert reply.search.applied + reply.search.late >= 1 and reply.search.worker_restarts == 0


def _plan_and_report(conn) -> None:
    """In a child: start a search beside the steps, send the search process's pid, then wait to be killed."""
    planner = LookaheadPlanner(params=LookaheadParams(mode="async", clock="wall", workers=1))
    planner.reset(0)
    planner.windows_for(busy_scene())
    conn.send(planner._process.process.pid)
    time.sleep(60)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc")
def test_the_search_process_ends_when_its_planning_process_is_killed():
    """A planning process killed by the server's watchdog leaves no search process behind."""
    import multiprocessing
    import signal

    context = multiprocessing.get_context("fork")
    here, there = context.Pipe()
    parent = context.Process(target=_plan_and_report, args=(there,), daemon=True)
    parent.start()
    assert here.poll(60)
    child = here.recv()
    os.kill(parent.pid, signal.SIGKILL)
    parent.join(5)
    tic = time.perf_counter()
    while time.perf_counter() - tic < 30:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        with open(f"/proc/{child}/stat") as stat:  # a zombie is gone too (its parent, the init, reaps it)
            if stat.read().split(") ")[-1].startswith("Z"):
                break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError("the search process outlived its planning process by 30 s")


def test_health_reports_the_searches_of_every_stream_since_the_start():
    """``/health`` sums the searches of the streams (an episode that a reset ended included); the flags that set
    the search name their range in one line."""
    pytest.importorskip("fastapi")
    import argparse

    from serve_support import TOKEN, ThreadServer

    from envs.commands.evaluate import check_search_arguments
    from envs.serve.app import PlannerService
    from envs.serve.client import PlannerClient
    from envs.serve.wire import scene_to_wire
    from sb3_graph.commands import UserError

    for mode, workers, message in (
        ("later", None, "^--search-mode must be one of sync, async, got 'later'$"),
        ("async", 0, "^--search-workers must be an integer from 1 to "),
        ("async", available_cores() + 1, "^--search-workers must be an integer from 1 to "),
    ):
        with pytest.raises(UserError, match=message):
            check_search_arguments(argparse.Namespace(search_mode=mode, search_workers=workers))
    service = PlannerService("lookahead", "CoopIntersection4Way-v0", shield=True, search_workers=1)
    assert service.prototype.planner.search.processes == 1
    env = gym.make("CoopIntersection4Way-v0", **evaluation_env_kwargs({}))
    env.reset(seed=3, options={"scenario": generate_scenario("4way", 60.0, 3, rate_range=(0.4, 0.4))})
    with ThreadServer(service, workers=0) as server:
        client = PlannerClient(server.url, token=TOKEN)
        stream = client.open("4way", seed=0)
        for k in range(280):  # 40 steps, more while the first search has not answered (a loaded machine)
            acc = client.step(stream, scene_to_wire(env.unwrapped.scene()))
            env.step(env.unwrapped.accelerations_to_action(np.array(acc)))
            time.sleep(0.02)
            if k >= 40 and client.last_search["started"] >= 2:
                break
        episode = client.last_search
        totals = client.health()["searches"]
        assert episode["started"] >= 2 and totals["started"] == episode["started"]
        assert totals["applied"] == episode["applied"] and totals["age_s_max"] == episode["age_s_max"]
        client.reset(stream, seed=1)
        assert client.health()["searches"]["started"] == episode["started"]  # the past episode is kept
        for stream_planner in service.streams.values():
            stream_planner.planner.planner.close()


def test_search_mode_async_puts_the_search_beside_the_steps_in_place_of_the_word_lookahead():
    from envs.commands.evaluate import checked_planners
    from envs.planners import make_planner

    planners = checked_planners(["lookahead", "glide"], shield=True, search_mode="async")
    assert [name for _, name in planners] == ["LookaheadAsync+shield", "Glide+shield"]
    assert make_planner(planners[0][0]).planner.search.mode == "async"
    assert checked_planners(["lookahead+shield"])[0] == ("lookahead+shield", "Lookahead+shield")
