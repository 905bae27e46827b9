"""A CSV without a time column (issue 10: acc_log.csv, ~40 static poses, 16,000 rows in g):
its rate is assumed, so the refusal says how to give it (``--csv-rate``), and with the rate
given the accelerometer calibrates."""
from __future__ import annotations

import json

import numpy as np

from mavcal.cli import main
from mavcal.pipeline import Options, calibrate_source
from mavcal.sources.reader import csv_rate_was_assumed, read_log


def test_csv_rate_assumed_refusal_says_what_to_do(real_dir, capsys):
    csv = real_dir / "acc_log.csv"
    assert csv_rate_was_assumed(read_log(csv))
    assert main(["-q", "calibrate", str(csv), "--accel-only"]) == 4
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "an accelerometer alone needs at least 6" in err[0] and "--csv-rate HZ" in err[0]


def test_csv_with_its_rate_given_calibrates(real_dir, capsys):
    csv = real_dir / "acc_log.csv"
    # the accelerometer fit itself (the CLI's --csv-rate 50 runs the same; its held-out check
    # refits 140 intervals, too slow for the suite)
    run = calibrate_source(read_log(csv, csv_rate_hz=50), Options(sensors="accel", holdout=False,
                                                                  uncertainty_draws=50))
    assert [(v.sensor, v.accepted) for v in run.verdicts] == [("accel0", True)]
    assert run.segmentation.coverage.n_orientations >= 30  # the ~40 poses are found
    p = run.mapping.new
    assert all(0.99 < p[f"INS_ACCSCAL_{a}"] < 1.01 for a in "XYZ")
    assert np.abs([p[f"INS_ACCOFFS_{a}"] for a in "XYZ"]).max() < 0.5
    capsys.readouterr()
    assert main(["-q", "segments", str(csv), "--csv-rate", "50", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["coverage"]["status"] == "ok"
    assert main(["-q", "segments", str(csv), "--csv-rate", "0"]) == 2
    assert "--csv-rate must be a positive" in capsys.readouterr().err
