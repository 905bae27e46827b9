"""mavcal's accelerometer parameters vs ArduPilot's own 6-position calibration, same poses.

The real logs 00000124.BIN, "2024-04-05 09-19-03.tlog" (same session, 2 Hz telemetry) and
"2023-05-17 12-18-48.tlog" (in ../shared/data/real, see SOURCES.md) contain ArduPilot's own
accelerometer calibration from the poses they record, with the result logged as PARM /
PARAM_VALUE. This compares mavcal's INS_ACCOFFS/INS_ACCSCAL with that result and expresses
the difference in mavcal's stated 1-sigma uncertainty.

    python benchmarks/real_6pose.py      # writes benchmarks/results/real_6pose.md
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mavcal.core.uncertainty import parameter_std
from mavcal.pipeline import Options, calibrate_source

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
OUT = Path(__file__).resolve().parent / "results"
# ArduPilot's own result, logged at the end of its calibration (SOURCES.md)
REFERENCE = {
    "00000124.BIN": ((0.0587, -0.0089, 0.1880), (0.9981, 0.9420, 0.9973)),
    "2024-04-05 09-19-03.tlog": ((0.0587, -0.0089, 0.1880), (0.9981, 0.9420, 0.9973)),
    "2023-05-17 12-18-48.tlog": ((0.0713, -0.0024, 0.3828), (0.9986, 0.9429, 0.9986)),
}



def compare(name: str):
    ref_ofs, ref_scl = REFERENCE[name]
    run = calibrate_source(str(REAL / name), Options(uncertainty_draws=50))
    cal, am = run.calibration, run.mapping.accel[0]
    sd = parameter_std(cal)  # the joint fit's stated uncertainty (the own fit of 6 poses has no spare equations)
    s_ofs = np.array([sd[f"b_a[{k}]"] for k in "xyz"])
    s_scl = np.array(am.new.scale) * np.array([sd[f"K_a[{k}{k}]"] for k in "123"]) / np.abs(np.diag(cal.accel.gain))
    d_ofs = np.array(am.new.ofs_mps2) - ref_ofs
    d_scl = np.array(am.new.scale) - ref_scl
    return {"name": name, "model": cal.model, "intervals": len(run.intervals_used), "ofs": np.array(am.new.ofs_mps2),
            "scl": np.array(am.new.scale), "d_ofs": d_ofs, "d_scl": d_scl, "s_ofs": s_ofs, "s_scl": s_scl,
            "z_ofs": d_ofs / s_ofs, "z_scl": d_scl / s_scl, "accepted": run.accepted,
            "failures": [f"{g.sensor} {g.name}" for g in run.gates.failures()], "exit_code": run.exit_code,
            "verdicts": run.verdicts, "written": run.params_to_write()}


def main() -> int:
    if not REAL.is_dir():
        print(f"real logs not found in {REAL}", file=sys.stderr)
        return 1
    rows = [compare(n) for n in REFERENCE]
    verdict = lambda r: "; ".join(f"{v.sensor} {'ok' if v.accepted else 'REJECTED'}" for v in r["verdicts"])  # noqa: E731
    f = lambda v, d=4: "(" + ", ".join(f"{x:.{d}f}" for x in v) + ")"  # noqa: E731
    L = ["# Accelerometer: mavcal vs ArduPilot's own 6-position calibration (same poses)\n",
         "Produced by `python benchmarks/real_6pose.py`. Differences are mavcal minus ArduPilot; z = difference / "
         "mavcal's stated 1-sigma of the joint fit (covariance inflated per sensor by its misfit). The "
         "accelerometer is written from its joint fit with compass 0 when that compass is accepted, else from its "
         "own fit.\n",
         "| log | model | intervals | INS_ACCOFFS diff (m/s^2) | sigma | z | INS_ACCSCAL diff | sigma | z | "
         "verdicts | exit |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['name']} | {r['model']} | {r['intervals']} | {f(r['d_ofs'])} | {f(r['s_ofs'])} | "
                 f"{f(r['z_ofs'], 2)} | {f(r['d_scl'], 5)} | {f(r['s_scl'], 5)} | {f(r['z_scl'], 2)} | "
                 f"{verdict(r)} | {r['exit_code']} |")
    L.append("")
    L.append("The compasses are rejected on these logs (an underwater ROV with large, pose-dependent magnetic "
             "disturbance and only six poses); with per-sensor verdicts the accelerometer is accepted and written "
             "alone (exit 7), the compasses keep their current values.")
    OUT.mkdir(exist_ok=True)
    (OUT / "real_6pose.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    from bench_output import output_dir  # --save / --out: where the results go (benchmarks/README.md)

    OUT, _ = output_dir(sys.argv[1:], strict=True)
    sys.exit(main())
