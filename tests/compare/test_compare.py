"""Method comparison: registry, same answer on every backend, resume, failures counted."""

import json

import numpy as np
import pytest

from bayescal.cli import main
from bayescal.compare import (
    METHODS, CompareConfig, compare_methods, comparison_from_records, parse_methods, register_method, run_trial,
    trial_rng,
)
from bayescal.compare.runner import TRIALS_FILE, run_trials
from bayescal.errors import InputError
from bayescal.identify import identify

TINY = dict(methods="ls,ridge", trials=4, dof=6, n_poses=12, n_eval=10, seed=3, progress=False)


@pytest.fixture(scope="module")
def reference(prs3):
    return compare_methods(prs3, **TINY)


def test_unknown_method_lists_the_known_ones():
    with pytest.raises(InputError, match="unknown method 'kalmn'.*ls .*ridge .*tsvd"):
        parse_methods("ls,kalmn")
    specs = parse_methods("ls, ridge:lam=0.1, tsvd:k=20")
    assert [s.label for s in specs] == ["ls", "ridge:lam=0.1", "tsvd:k=20"]
    assert specs[1].options == (("lam", 0.1),) and specs[2].options == (("k", 20),)
    with pytest.raises(InputError, match="key=value"):
        parse_methods("ridge:0.1")
    with pytest.raises(InputError, match="twice"):
        parse_methods("ls,ls")


def test_adding_a_method_is_one_registry_entry(prs3):
    register_method("ridge_strong", lambda model, *, free, lam: identify(model, method="ridge", lam=lam, free=free),
                    lam=1e4, help="test entry")
    try:
        cfg = CompareConfig(machine_text=prs3.to_toml(), methods="ridge,ridge_strong", trials=1, n_poses=12, n_eval=10)
        rec = run_trial(cfg.to_dict(), 0)
        # a very strong prior keeps the estimate near nominal: a larger output error than lam = 1
        assert rec["methods"]["ridge_strong"]["rms_position"] > rec["methods"]["ridge"]["rms_position"]
    finally:
        del METHODS["ridge_strong"]


def test_trials_are_seeded_by_index():
    a = trial_rng(5, 7).normal(size=3)
    b = np.random.default_rng(np.random.SeedSequence(5).spawn(10)[7]).normal(size=3)
    np.testing.assert_array_equal(a, b)


def test_report_and_json(reference):
    assert reference.n_trials == 4 and reference.labels == ("ls", "ridge")
    assert reference.summary["ridge"]["failures"] == 0
    text = reference.report()
    assert "Wilcoxon" in text and "ridge" in text
    json.dumps(__import__("bayescal.io.answers", fromlist=["to_jsonable"]).to_jsonable(reference.to_dict()))
    # calibration helps: far below the uncalibrated error
    assert reference.summary["ridge"]["median"] < 0.2 * np.median(reference.nominal)


# a LocalCluster shutting down on a loaded machine can leave sockets for the garbage collector
# (LIBRARIES.md: heartbeat errors on close); that is dask's housekeeping, not a result of this test
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.filterwarnings("ignore::ResourceWarning")
def test_same_table_in_process_and_on_a_two_worker_dask_cluster(prs3, reference):
    on_dask = compare_methods(prs3, **TINY, dask_workers=2)
    assert on_dask.info["backend"].startswith("dask")
    assert json.dumps(on_dask.table(), default=str) == json.dumps(reference.table(), default=str)


def test_resume_after_an_interrupted_run_gives_the_same_table(prs3, reference, tmp_path):
    out = tmp_path / "run"
    first = compare_methods(prs3, **TINY, out=out)
    assert first.info["ran"] == 4
    lines = (out / TRIALS_FILE).read_text().splitlines()
    # interrupted: two trials saved, the third torn mid-write
    (out / TRIALS_FILE).write_text("\n".join(lines[:2]) + "\n" + lines[2][:25])
    resumed = compare_methods(prs3, **TINY, out=out)
    assert resumed.info["resumed"] == 2 and resumed.info["ran"] == 2
    assert json.dumps(resumed.table(), default=str) == json.dumps(reference.table(), default=str)
    assert len((out / TRIALS_FILE).read_text().splitlines()) == 4
    again = compare_methods(prs3, **TINY, out=out)
    assert again.info["ran"] == 0
    with pytest.raises(InputError, match="different configuration"):
        compare_methods(prs3, **{**TINY, "seed": 4}, out=out)


def test_least_squares_failures_are_counted_separately(prs3):
    cfg = CompareConfig(machine_text=prs3.to_toml(), methods="ls,ridge", trials=2, dof=5, n_poses=12, n_eval=10,
                        free="all")
    records, info = run_trials(cfg, progress=False)
    cmp = comparison_from_records(records, cfg)
    assert cmp.summary["ls"]["failures"] == 2 and np.all(np.isnan(cmp.errors["ls"]))
    assert cmp.summary["ridge"]["failures"] == 0
    assert "ill-posed" in cmp.failure_messages["ls"][0]
    assert cmp.pairs[0].n == 0 and "failures (counted separately" in cmp.report()


def test_cli_compare_writes_table_json_and_figures(tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(["compare", "--machine", "examples/prs3/machine.toml", "--methods", "ridge,tsvd", "--trials", "2",
               "--poses", "12", "--eval-poses", "10", "--out", str(out), "--quiet"])
    assert rc == 0
    for name in ("table.txt", "comparison.json", "trials.jsonl", "compare_errors.png", "compare_differences.png",
                 "compare_win_rates.png"):
        assert (out / name).exists(), name
    rc = main(["compare", "--machine", "examples/prs3/machine.toml", "--methods", "nope", "--trials", "2"])
    assert rc == 2 and "known methods" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.filterwarnings("ignore::ResourceWarning")
@pytest.mark.filterwarnings("ignore:Port .* is already in use:UserWarning")
def test_same_table_through_a_running_scheduler_address(prs3, reference):
    from distributed import LocalCluster

    # an in-process cluster keeps the test cheap; the scheduler is reached by its tcp address
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        via = compare_methods(prs3, **TINY, scheduler=cluster.scheduler_address)
    assert via.info["backend"] == f"dask ({cluster.scheduler_address})"
    assert json.dumps(via.table(), default=str) == json.dumps(reference.table(), default=str)
    with pytest.raises(InputError, match="not both"):
        compare_methods(prs3, **TINY, scheduler="tcp://127.0.0.1:1", dask_workers=2)


def test_same_table_in_process_and_on_two_local_processes(prs3, reference):
    on_procs = compare_methods(prs3, **TINY, workers=2)
    assert on_procs.info["backend"] == "local processes (2)"
    assert json.dumps(on_procs.table(), default=str) == json.dumps(reference.table(), default=str)


class _KillFirstExecutingWorker:
    """dask worker plugin: the first task to start executing anywhere kills its worker process.

    A marker file created with O_EXCL makes it exactly one death across all workers (and across the
    worker the nanny restarts, which gets the plugin again).
    """

    name = "bayescal-test-kill-first-worker"

    def __init__(self, marker):
        self.marker = str(marker)

    def setup(self, worker):
        pass

    def teardown(self, worker):
        pass

    def transition(self, key, start, finish, **kwargs):
        import os

        if finish == "executing":
            try:
                fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return
            os.write(fd, str(os.getpid()).encode())
            os.close(fd)
            os._exit(1)  # the process dies mid-task, as a crashed or killed worker would


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.filterwarnings("ignore::ResourceWarning")
@pytest.mark.filterwarnings("ignore:Port .* is already in use:UserWarning")
def test_a_worker_dying_mid_trial_does_not_stop_the_comparison(prs3, reference, tmp_path):
    import logging
    import os
    from concurrent.futures import ThreadPoolExecutor

    from distributed import Client, LocalCluster
    from distributed.diagnostics.plugin import WorkerPlugin

    logging.getLogger("distributed").setLevel(logging.CRITICAL)  # the death is logged loudly; it is the test
    marker = tmp_path / "killed_pid"
    plugin = type("KillFirst", (_KillFirstExecutingWorker, WorkerPlugin), {})(marker)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster, timeout="30s") as client:
        client.register_plugin(plugin)
        pids_before = set(client.run(os.getpid).values())
        with ThreadPoolExecutor(1) as ex:
            # bounded: a hang (e.g. the task never rescheduled) fails the test instead of blocking the suite
            survived = ex.submit(compare_methods, prs3, **TINY, scheduler=cluster.scheduler_address).result(timeout=180)
        killed = int(marker.read_text())
    assert killed in pids_before  # one of the two original workers died mid-task ...
    assert survived.info["ran"] == TINY["trials"]  # ... and every trial still finished, with the same table
    assert json.dumps(survived.table(), default=str) == json.dumps(reference.table(), default=str)


def test_compare_map_is_identify_map():
    # `compare --methods map` compares what `identify --method map` answers (issue 31: it was ridge lam=1)
    import bayescal
    from bayescal.compare.methods import METHODS
    from bayescal.identify.calibrate import calibrate

    from ..conftest import PRS3_FILE, ROOT

    model = bayescal.load(PRS3_FILE, ROOT / "examples" / "prs3" / "recording.csv").fit_model
    got = METHODS["map"].fn(model, free="auto")
    want = calibrate(model, method="map").result
    np.testing.assert_array_equal(got.theta, want.theta)
    ridge = identify(model, method="ridge", lam=1.0, free="auto")
    assert np.max(np.abs(ridge.theta - got.theta)) > 0  # the old entry's answer differs on this recording


def test_mcmc_trials_can_stop_at_an_ess(prs3, monkeypatch):
    # each trial's chain stops at the ESS asked for, as identify --ess; the option is checked before any trial
    import bayescal.bayes.mcmc as mcmc

    specs = parse_methods("mcmc:ess=1000;steps=3000")
    assert specs[0].options == (("ess", 1000), ("steps", 3000))
    for bad in ("mcmc:ess=0", "mcmc:ess=-5", "mcmc:ess=nan", "mcmc:ess=inf", "mcmc:ess=abc"):
        with pytest.raises(InputError, match=r"ess"):
            parse_methods(bad)
    runs = []
    sample = mcmc.sample_posterior
    monkeypatch.setattr(mcmc, "sample_posterior", lambda *a, **k: runs.append(r := sample(*a, **k)) or r)
    res = compare_methods(prs3, methods="mcmc:ess=1000;steps=3000", trials=1, dof=6, n_poses=12, n_eval=10, seed=3,
                          progress=False)
    d = res.to_dict()
    assert d["summary"]["mcmc:ess=1000;steps=3000"]["failures"] == 0, d["failure_messages"]
    # the trial's chain stopped at the ESS, well short of its 3,000 steps
    assert len(runs) == 1 and runs[0].min_ess == 1000 and runs[0].n_steps < 3000
