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


def test_one_version_read_from_the_package_metadata():
    """`mavcal --version`, `mavcal.__version__` and the JSON report's `mavcal_version` are the installed
    distribution's version (pyproject.toml's, through its metadata), not a second number in the code."""
    from importlib.metadata import version

    import mavcal
    from mavcal.errors import SourceError
    from mavcal.report.json import refusal_json

    installed = version("mavcal")
    out = subprocess.run([sys.executable, "-m", "mavcal", "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == f"mavcal {installed}"
    assert mavcal.__version__ == installed
    assert refusal_json("x.tlog", SourceError("x.tlog: unreadable"))["mavcal_version"] == installed


def test_help_does_not_read_the_package_metadata():
    """The version is read when asked for: importlib.metadata costs `mavcal --help` ~10-60 ms."""
    code = "import sys, mavcal.cli; print('importlib.metadata' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "False"
