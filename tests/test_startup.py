"""`mavcal --help` must start at once: the package import does not pull in the engine."""
import subprocess
import sys


def test_cli_import_does_not_load_scipy_or_pymavlink():
    code = ("import sys, mavcal.cli; heavy = [m for m in ('scipy', 'pymavlink', 'matplotlib') if m in sys.modules]; "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == ""


def test_public_api_still_importable_from_the_package():
    import mavcal
    from mavcal import Calibration, calibrate, calibrate_multi, estimate_orientations, reconstruction_error

    assert mavcal.calibrate is calibrate and callable(calibrate_multi)
    assert Calibration.__name__ == "Calibration" and callable(estimate_orientations)
    assert callable(reconstruction_error)
    assert "calibrate" in dir(mavcal)
