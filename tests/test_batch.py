"""Many logs at once: parallel calibration and the fleet table."""
from __future__ import annotations

import os
import pickle
from dataclasses import fields

import pytest

from mavcal.batch import DRIFT_COMPASS_MGAUSS, BatchRow, calibrate_many, format_fleet_table
from mavcal.errors import UsageError
from mavcal.pipeline import Options

FAST = Options(uncertainty_draws=50)


@pytest.fixture(scope="module")
def batch(sitl_dir, tmp_path_factory):
    bad = tmp_path_factory.mktemp("batch") / "corrupt.tlog"
    bad.write_bytes(os.urandom(3000).replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00"))
    sources = [str(sitl_dir / "sitl01.tlog"), str(bad), str(sitl_dir / "sitl02.tlog")]
    seen = []
    rows = calibrate_many(sources, FAST, jobs=2, progress=lambda d, t, r: seen.append((d, t, r.source)))
    return sources, rows, seen


def test_two_ok_rows_and_one_error_row(batch):
    sources, rows, seen = batch
    assert [r.source for r in rows] == sources  # input order, whatever the completion order
    ok = [r for r in rows if r.ok]
    bad = [r for r in rows if not r.ok]
    assert len(ok) == 2 and len(bad) == 1
    assert bad[0].source == sources[1]
    assert bad[0].exit_code == 3 and "not a tlog" in bad[0].error
    assert bad[0].accepted is None and bad[0].compass_ofs_new is None
    for r in ok:
        assert r.exit_code == 0 and r.accepted and r.error is None and r.failed_gates == ()
        assert r.sysid == 1 and r.compass_dev_id == 97539 and r.accel_id == 2753028
        assert r.heading_95_deg < 0.5 and r.tilt_95_deg < 0.05
        assert r.model and r.n_intervals >= 14
    r1, r2 = rows[0], rows[2]
    assert r1.n_intervals == 21 and r2.n_intervals == 15
    # both SITL vehicles were given COMPASS_OFS (10, -20, 30) on purpose; the truth is far off
    assert r1.compass_ofs_old == pytest.approx((10.0, -20.0, 30.0))
    assert r1.compass_ofs_change_mgauss == pytest.approx(
        sum((a - b) ** 2 for a, b in zip(r1.compass_ofs_new, r1.compass_ofs_old)) ** 0.5)
    assert r1.compass_ofs_change_mgauss > 100 and r2.compass_ofs_change_mgauss > 100
    assert r1.accel_ofs_change_mps2 > 0.1 and r1.accel_scale_change > 0.01
    assert sorted(d for d, _, _ in seen) == [1, 2, 3] and {t for _, t, _ in seen} == {3}


def test_rows_are_small_and_plain(batch):
    _, rows, _ = batch
    for r in rows:
        assert len(pickle.dumps(r)) < 4000  # a summary, never the sample arrays
        for f in fields(r):
            v = getattr(r, f.name)
            items = v if isinstance(v, tuple) else (v,)
            if f.name == "sensors":  # the verdicts: a sensor name, a yes/no and reasons in words
                items = tuple(x for s in v for x in (s.sensor, s.accepted, *s.reasons))
            assert all(x is None or isinstance(x, (str, int, float, bool)) for x in items), f.name


def test_fleet_table_mentions_both_logs(batch):
    sources, rows, _ = batch
    text = format_fleet_table(rows)
    lines = text.splitlines()
    i1 = next(i for i, ln in enumerate(lines) if "sitl01.tlog" in ln)
    i2 = next(i for i, ln in enumerate(lines) if "sitl02.tlog" in ln)
    ib = next(i for i, ln in enumerate(lines) if "corrupt.tlog" in ln)
    assert "ERROR 3" in lines[ib] and "not a tlog" in lines[ib + 1]
    assert max(i1, i2) < ib  # failed logs last
    assert "DRIFT" in lines[i1] and "DRIFT" in lines[i2]
    assert "3 logs: 2 accepted, 0 partly accepted, 0 rejected by the gates, 1 failed" in text


def test_sequential_matches_parallel(batch, sitl_dir):
    _, rows, _ = batch
    [seq] = calibrate_many([str(sitl_dir / "sitl01.tlog")], FAST, jobs=1)
    par = rows[0]
    assert seq.compass_ofs_new == par.compass_ofs_new and seq.heading_95_deg == par.heading_95_deg


def test_jobs_must_be_positive():
    with pytest.raises(UsageError):
        calibrate_many(["x.tlog"], FAST, jobs=0)
    assert calibrate_many([], FAST, jobs=4) == []


def _row(src, sysid, dc, accepted=True, **kw):
    return BatchRow(source=src, ok=True, exit_code=0 if accepted else 4, sysid=sysid, compass_dev_id=97539,
                    accel_id=2753028, accepted=accepted, heading_95_deg=0.1, tilt_95_deg=0.01,
                    compass_ofs_old=(0.0, 0.0, 0.0), compass_ofs_new=(dc, 0.0, 0.0), compass_ofs_change_mgauss=dc,
                    accel_ofs_change_mps2=0.01, accel_scale_change=0.001, model="ardupilot", n_intervals=12, **kw)


def test_fleet_table_orders_vehicles_by_drift():
    rows = [_row("a/v1.tlog", 1, 3.0), _row("b/v2_old.tlog", 2, 5.0), _row("b/v2_new.tlog", 2, 80.0),
            _row("c/v3.tlog", 3, 30.0, accepted=False, failed_gates=("data intervals: only 4 still intervals",)),
            BatchRow(source="d/broken.bin", ok=False, error="no IMU data", exit_code=3)]
    text = format_fleet_table(rows)
    table = [ln for ln in text.splitlines() if ln and not ln.startswith(" ")]
    names = ("v1.tlog", "v2_old", "v2_new", "v3.tlog", "broken")
    order = sorted(names, key=lambda n: next(i for i, ln in enumerate(table) if n in ln))
    # vehicle 2 (one log changed 80 mGauss) first, its logs biggest change first; then 3, then 1; errors last
    assert order == ["v2_new", "v2_old", "v3.tlog", "v1.tlog", "broken"]
    lines = {n: next(ln for ln in table if n in ln) for n in names}
    assert "DRIFT" in lines["v2_new"] and "drift?" in lines["v3.tlog"]  # above 25 mGauss, v3 rejected
    assert "DRIFT" not in lines["v2_old"] and "DRIFT" not in lines["v1.tlog"]
    assert "REJECTED" in lines["v3.tlog"] and "gate data intervals: only 4 still intervals" in text
    assert ("5 logs: 3 accepted, 0 partly accepted, 1 rejected by the gates, 1 failed; 3 vehicle/instance group(s)"
            in text)
    assert "exit code 3 (the worst" in text  # the failure, not the largest code
    assert f"compass offsets > {DRIFT_COMPASS_MGAUSS:g} mGauss" in text and "scale > 0.01): v2_new.tlog\n" in text
    assert "rejected calibrations (not trustworthy, see the gates): v3.tlog" in text
    assert format_fleet_table([]) == "no logs"
