"""Issue 11: one recording's fits in forked worker processes (mavcal.workers.ForkPool,
Options.workers, ``mavcal calibrate --jobs``): the same results to the bit, errors per job."""
from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest

from mavcal import workers as W
from mavcal.errors import InsufficientDataError
from mavcal.pipeline import Options, calibrate_prepared, prepare
from mavcal.report.json import to_json
from mavcal.sources.reader import read_log

pytestmark = pytest.mark.skipif(not W.can_fork(), reason="needs fork")


def _outcomes(pool, fn, items, done=None):
    """The outcome of every item, in the order of ``items`` (ForkPool.run with no follow-ups)."""
    out = {}

    def keep(item, outcome):
        out[item] = outcome
        return []

    pool.run(fn, items, keep, done)
    return [out[k] for k in items]


def _job(shared, item):
    """Sum of the inherited array times ``item``, and the process it ran in."""
    if item < 0:
        raise InsufficientDataError(f"item {item} refused")
    return float(shared["x"].sum()) * item, os.getpid()


def test_fork_pool_runs_jobs_in_workers_that_inherit_the_shared_data():
    shared = {"x": np.arange(1_000_000, dtype=float)}  # inherited, never pickled
    done = []
    with W.ForkPool(shared, 2) as pool:
        out = _outcomes(pool, _job, [1, 2, -1, 3], done=done.append)
        again = _outcomes(pool, _job, [4, 5])  # the same workers, still holding the shared data
    assert [ok for ok, _ in out] == [True, True, False, True]
    assert [v[0] for ok, v in out if ok] == [shared["x"].sum() * k for k in (1, 2, 3)]
    assert isinstance(out[2][1], InsufficientDataError) and "item -1 refused" in str(out[2][1])
    assert all(v[1] != os.getpid() for ok, v in out + again if ok)  # not this process
    assert done == [1, 2, 3, 4] and again[1][1][0] == shared["x"].sum() * 5
    assert W._SHARED is None  # released at exit


def test_fork_pool_with_one_worker_or_no_fork_runs_here(monkeypatch):
    with W.ForkPool({"x": np.ones(3)}, 1) as pool:
        out = _outcomes(pool, _job, [1, -2])
    assert out[0] == (True, (3.0, os.getpid())) and not out[1][0]
    monkeypatch.setattr(W, "can_fork", lambda: False)
    with W.ForkPool({"x": np.ones(3)}, 4) as pool:
        assert pool.workers == 1 and _outcomes(pool, _job, [2])[0] == (True, (6.0, os.getpid()))
    assert 1 <= W.default_workers() <= 4 and W.default_workers(most=1) == 1


_PARENT = os.getpid()


def _dies_in_worker(shared, item):
    if os.getpid() != _PARENT and item % 2:
        os.kill(os.getpid(), signal.SIGKILL)  # as the kernel's out-of-memory killer would end it
    return shared * item, os.getpid()


def test_a_worker_that_dies_fails_its_job_alone_with_one_line():
    """Issue 23: the job whose worker was killed fails with WorkerDiedError (exit code 70 at
    the CLI), the others give their results, and the next jobs get a new worker."""
    with W.ForkPool(10, 2) as pool:
        out = _outcomes(pool, _dies_in_worker, [1, 2, 4])
        again = _outcomes(pool, _dies_in_worker, [6])
        assert len(pool.pids) <= 2
    assert not out[0][0] and isinstance(out[0][1], W.WorkerDiedError) and out[0][1].exit_code == 70
    assert "killed by signal 9 (SIGKILL) (out of memory?)" in str(out[0][1]) and "\n" not in str(out[0][1])
    assert [v[0] for _, v in out[1:]] == [20, 40] and again[0][0] and again[0][1][0] == 60
    assert W._SHARED is None


def _tens(shared, item):
    return item * 10, os.getpid()


@pytest.mark.parametrize("workers", [1, 2])
def test_run_starts_each_follow_up_job_when_the_job_it_needs_is_done(workers):
    """ForkPool.run: the items ``then`` returns for a finished job run too (2 follows 1, 3
    follows 2, 12 follows 11...), each after its parent; with one worker, first in, first out."""
    seen, done = [], []

    def then(item, outcome):
        assert outcome[0] and outcome[1][0] == item * 10
        seen.append(item)
        return [item + 1] if item % 10 < 3 else []

    with W.ForkPool(None, workers) as pool:
        pool.run(_tens, [1, 11], then, done=done.append)
    assert sorted(seen) == [1, 2, 3, 11, 12, 13] and done == [1, 2, 3, 4, 5, 6]
    assert all(seen.index(k) < seen.index(k + 1) for k in (1, 2, 11, 12))
    if workers == 1:
        assert seen == [1, 11, 2, 12, 3, 13]


def test_an_exception_in_then_stops_the_run():
    seen = []

    def then(item, outcome):
        seen.append(item)
        if item == 2:
            raise ValueError("the primary fit failed")
        return [item + 1]

    for workers in (1, 2):
        seen.clear()
        with W.ForkPool(None, workers) as pool, pytest.raises(ValueError, match="primary"):
            pool.run(_tens, [1], then)
        assert seen == [1, 2]  # 3 never ran


def test_follow_up_jobs_run_after_a_worker_dies():
    got = {}

    def then(item, outcome):
        got[item] = outcome
        return [item + 1] if item in (1, 2) else []

    with W.ForkPool(10, 2) as pool:
        pool.run(_dies_in_worker, [1, 2], then)  # 1 and 3 kill their workers; 2 follows 1 anyway
    assert sorted(got) == [1, 2, 3] and got[2] == (True, (20, got[2][1][1]))
    assert not got[1][0] and not got[3][0]


def test_other_exceptions_propagate():
    with W.ForkPool({"x": None}, 2) as pool, pytest.raises(AttributeError):
        _outcomes(pool, _job, [1, 2])  # None.sum(): a bug, not bad input, is raised here


def test_fits_in_two_workers_equal_the_fits_in_this_process(sitl_dir):
    prep = prepare(read_log(str(sitl_dir / "sitl02.tlog")))
    stages = []

    class Progress:
        def stage(self, name, done, total):
            stages.append((name, done, total))

    one = calibrate_prepared(prep, Options(workers=1))
    two = calibrate_prepared(prep, Options(workers=2), progress=Progress())
    assert len(two.others) == len(one.others) >= 2 and two.log is prep.log and two.raw is prep.raw
    assert all(r.segmentation is prep.segmentation for r in two.others)
    assert json.dumps(to_json(two), sort_keys=True) == json.dumps(to_json(one), sort_keys=True)
    assert two.warnings == one.warnings and two.params_to_write() == one.params_to_write()
    assert stages[-1][1] == stages[-1][2] and len(stages) >= 1 + len(two.others) + 1


def test_a_held_out_check_is_cut_into_even_slices_of_at_least_two_per_worker():
    from mavcal.core.accel_fit import HOLDOUT_FOLDS
    from mavcal.fits import _holdout_slices

    assert _holdout_slices(1) == 1
    for workers in (2, 3, 4, 5, 8):
        s = _holdout_slices(workers)
        assert s >= 2 * workers and (HOLDOUT_FOLDS % s == 0 or s == 2 * workers)
    assert _holdout_slices(2) == 5 and HOLDOUT_FOLDS == 10


def test_held_out_refits_in_slices_combine_to_the_whole_check_to_the_bit():
    """The held-out check split into K slices of its refits (one per worker) gives, put back in
    order, exactly the number of the whole check; a check that cannot run stays NaN."""
    from mavcal.core.calibrate import calibrate
    from mavcal.judging.quality import holdout_errors, holdout_part, holdout_rms
    from mavcal.sim.paper import simulate

    for n in (24, 90):  # leave-one-out, then 10-fold
        sim = simulate(n, seed=3, samples=(60, 80))
        cal = calibrate(sim.accel_sets, sim.mag_sets, seed=0)
        whole = holdout_errors(sim.accel_sets, sim.mag_sets, cal)
        for K in (1, 2, 3, 5):  # fit_recording cuts a 10-fold check into 5 slices for 2 workers
            parts = [holdout_part(sim.accel_sets, sim.mag_sets, cal, part=(k, K)) for k in range(K)]
            assert holdout_rms(parts) == whole and np.all(np.isfinite(whole))
    tiny = simulate(5, seed=3, samples=(60, 80))
    cal5 = calibrate(tiny.accel_sets, tiny.mag_sets, seed=0, model="offsets-scales")
    assert holdout_part(tiny.accel_sets[:4], tiny.mag_sets[:4], cal5) is None
    assert np.all(np.isnan(holdout_rms([None]))) and np.all(np.isnan(holdout_rms([])))
