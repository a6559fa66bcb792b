"""Storage URLs of the tuning command: the accepted forms, clear errors, heartbeats of killed workers."""

import importlib.util
import time

import optuna
import pytest
from optuna.trial import TrialState

from sb3_graph.tuning.storage import (
    ACCEPTED_FORMS,
    StorageURLError,
    make_storage,
    postgres_driver_url,
    redact,
    storage_kind,
)

optuna.logging.set_verbosity(optuna.logging.WARNING)


@pytest.mark.parametrize(
    "url, kind",
    [
        ("sqlite:///studies/w.db", "sqlite"),
        ("sqlite:////abs/w.db", "sqlite"),
        ("postgresql://u:p@localhost:5432/db", "postgresql"),
        ("postgresql+psycopg2://u@host/db", "postgresql"),
        ("postgres://u:p@h/db", "postgresql"),
        ("journal:///mnt/shared/w.log", "journal"),
        ("journal://studies/w.log", "journal"),
    ],
)
def test_storage_kind_accepts_the_documented_forms(url, kind):
    assert storage_kind(url) == kind


@pytest.mark.parametrize("url", ["", "mysql://u@h/db", "studies/w.db", "sqlite:///", "journal://", "postgresql://h"])
def test_bad_url_names_the_accepted_forms(url):
    with pytest.raises(StorageURLError) as info:
        storage_kind(url)
    for form in ACCEPTED_FORMS:
        assert form in str(info.value)


def test_redact_hides_the_password():
    assert redact("postgresql://user:secret@host:5432/db") == "postgresql://user:***@host:5432/db"
    assert redact("sqlite:///a.db") == "sqlite:///a.db"


def test_postgres_url_names_an_installed_driver():
    assert postgres_driver_url("postgresql+psycopg://u@h/db").startswith("postgresql+psycopg://")
    try:
        url = postgres_driver_url("postgres://u@h/db")
    except StorageURLError as error:  # no driver installed: the message says what to install
        assert "psycopg2-binary" in str(error)
    else:
        assert url.split("://")[0] in ("postgresql+psycopg2", "postgresql+psycopg")


def test_sqlite_and_journal_create_their_folder_and_keep_trials(tmp_path):
    for url in (f"sqlite:///{tmp_path}/a/b/s.db", f"journal://{tmp_path}/c/d/s.log"):
        study = optuna.create_study(study_name="s", storage=make_storage(url), load_if_exists=True)
        study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
        again = optuna.load_study(study_name="s", storage=make_storage(url))
        assert [t.state for t in again.trials] == [TrialState.COMPLETE] * 2
    assert (tmp_path / "a" / "b" / "s.db").is_file()
    assert (tmp_path / "c" / "d" / "s.log").is_file()


def test_unreachable_server_is_a_clear_error():
    # Without a PostgreSQL driver (the README's `pip install -e ".[test]"` has none) the clear
    # error is the one that asks for the driver; with one, the server cannot be reached.
    has_driver = any(importlib.util.find_spec(name) for name in ("psycopg2", "psycopg"))
    expected = "cannot open storage" if has_driver else "needs a driver"
    with pytest.raises(StorageURLError, match=expected):
        make_storage("postgresql://u:p@127.0.0.1:1/db")


def test_missing_driver_is_a_clear_error(monkeypatch):
    import sb3_graph.tuning.storage as storage

    real = importlib.util.find_spec
    monkeypatch.setattr(
        storage.importlib.util, "find_spec", lambda name, *a: None if name.startswith("psycopg") else real(name, *a)
    )
    with pytest.raises(StorageURLError, match=r'pip install "sb3-graph\[postgres\]"'):
        make_storage("postgresql://u:p@127.0.0.1:1/db")


def test_storage_folder_that_cannot_be_made_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    for url in (f"sqlite:///{blocker}/sub/s.db", f"journal://{blocker}/sub/s.log"):
        with pytest.raises(StorageURLError, match="cannot create folder"):
            make_storage(url)


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")  # the dead trial is made with study.ask
@pytest.mark.parametrize("max_retry", [0, 1])
@pytest.mark.parametrize("form", ["sqlite:///{}/hb.db", "journal://{}/hb.log"])
def test_heartbeat_fails_the_trial_of_a_killed_worker(tmp_path, form, max_retry):
    url = form.format(tmp_path)
    storage = make_storage(url, heartbeat_interval=1, grace_period=1, max_retry=max_retry)
    study = optuna.create_study(study_name="hb", storage=storage)
    # A worker that died mid-trial: the trial is RUNNING and its last heartbeat grows old.
    dead = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)})
    storage.record_heartbeat(dead._trial_id)
    time.sleep(2.5)
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1 + max_retry)
    states = [t.state for t in study.get_trials()]
    assert states[0] == TrialState.FAIL
    assert states.count(TrialState.COMPLETE) == 1 + max_retry
    if max_retry:  # the failed trial was retried with its parameters
        retried = [t for t in study.get_trials() if t.system_attrs.get("failed_trial") == dead.number]
        assert len(retried) == 1 and retried[0].params["x"] == dead.params["x"]


@pytest.mark.filterwarnings("ignore:Heartbeat of storage")  # the live trial is made with study.ask
def test_journal_heartbeat_keeps_a_live_trial_running(tmp_path):
    storage = make_storage(f"journal://{tmp_path}/live.log", heartbeat_interval=1, grace_period=2)
    study = optuna.create_study(study_name="live", storage=storage)
    live = study.ask()
    for _ in range(3):  # a worker that is still alive keeps beating
        time.sleep(0.8)
        storage.record_heartbeat(live._trial_id)
    assert storage._get_stale_trial_ids(study._study_id) == []
    time.sleep(2.5)
    assert storage._get_stale_trial_ids(study._study_id) == [live._trial_id]
    # Another process that opens the same journal sees the same heartbeats.
    other = make_storage(f"journal://{tmp_path}/live.log", heartbeat_interval=1, grace_period=2)
    assert other._get_stale_trial_ids(study._study_id) == [live._trial_id]
