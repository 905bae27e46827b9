"""Checks that an *installed* mavcal serves its capture page from its own files (CI's wheel step).

``.ci/run`` installs the wheel into a fresh virtual environment outside the checkout and runs
there, among others, ``python -m mavcal.testing.installed --not-under CHECKOUT``:

1. ``mavcal`` is imported from the environment's ``site-packages`` (not from ``CHECKOUT``, nor
   from an editable install pointing at it), and the capture page's files are there;
2. a loopback vehicle (:class:`mavcal.testing.vehicle.TestVehicle`) is started in this process
   and the environment's ``mavcal capture --connect DEVICE --ui --no-browser`` is run against
   it as a user runs it (the console script beside this interpreter);
3. the page (``/``), its script and its style are fetched over HTTP with the session's token,
   as the browser would; each must be what the installed package holds, byte for byte (the
   page with the token the server writes into its links);
4. the page's state (``/state``) follows the capture once the vehicle's data arrive; then the
   capture is stopped with Ctrl-C (SIGINT), as a user stops it, and must end within
   :data:`STOP_S`, neither killed nor with an internal error (exit 70); the vehicle is stopped.

A wheel built without the page's files fails at 1 (and, were that check skipped, at 3: the
server has no page to send). One line per check on stdout; exit status 0 when all pass, 1 otherwise.
Without ``--not-under`` step 1 only checks that the files are in the imported package (the
editable install of the tests).

    python -m mavcal.testing.installed [--not-under DIR] [--timeout S]
"""
from __future__ import annotations

import argparse
import http.client
import json
import os
import re
import signal
import subprocess
import sys
import sysconfig
import threading
import time
from importlib import resources
from pathlib import Path

#: the page's files (mavcal/capture/page/), each with its path on the server
ASSETS = {"/": "index.html", "/page.js": "page.js", "/page.css": "page.css"}
#: seconds the capture may take to end after Ctrl-C
STOP_S = 20.0

_URL = re.compile(r"capture page: http://127\.0\.0\.1:(\d+)/\?t=([0-9A-Za-z_-]+)")


class CheckFailed(Exception):
    """One check failed (the message says which and what was seen)."""


def _under(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def check_location(not_under: Path | None) -> Path:
    """The imported package's folder, after checking it is the environment's (step 1)."""
    import mavcal

    pkg = Path(mavcal.__file__).resolve().parent
    purelib = Path(sysconfig.get_paths()["purelib"])
    if not_under is not None:
        if _under(pkg, not_under):
            raise CheckFailed(f"mavcal was imported from the checkout ({pkg}), not from the installed package")
        if not _under(pkg, purelib):
            raise CheckFailed(f"mavcal was imported from {pkg}, not from this environment's {purelib}")
    page = resources.files("mavcal.capture").joinpath("page")
    missing = [name for name in ASSETS.values() if not page.joinpath(name).is_file()]
    if missing:
        raise CheckFailed(f"the installed package lacks the capture page's {', '.join(missing)} (in {pkg})")
    return pkg


def _get(port: int, token: str, path: str) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", f"{path}?t={token}", headers={"Host": f"127.0.0.1:{port}"})
        r = conn.getresponse()
        return r.status, r.read()
    except (OSError, http.client.HTTPException) as exc:  # e.g. the server failed on a missing file
        raise CheckFailed(f"GET {path}: no answer: {type(exc).__name__}: {exc}") from None
    finally:
        conn.close()


def _wait_capturing(port: int, token: str, proc: subprocess.Popen, deadline: float) -> str:
    """The page's phase once the capture runs (its first status from the vehicle), as a user
    sees it before pressing Ctrl-C."""
    phase = "starting"
    while time.monotonic() < deadline and proc.poll() is None:
        status, body = _get(port, token, "/state")
        if status != 200:
            raise CheckFailed(f"GET /state: HTTP {status}: {body[:200]!r}")
        phase = json.loads(body).get("phase", "")
        if phase != "starting":
            return phase
        time.sleep(0.2)
    raise CheckFailed(f"the page stayed at phase {phase!r}: no capture status from the vehicle "
                      f"(mavcal capture exit {proc.poll()})")


def _mavcal_command() -> list[str]:
    """The environment's console script (beside this interpreter), as a user runs it."""
    script = Path(sys.executable).with_name("mavcal.exe" if os.name == "nt" else "mavcal")
    if not script.exists():
        raise CheckFailed(f"no console script {script}: the package's [project.scripts] entry was not installed")
    return [str(script)]


def _read_lines(stream, lines: list[str], seen: threading.Event) -> None:
    for line in stream:
        lines.append(line.rstrip("\n"))
        if _URL.search(line):
            seen.set()
    seen.set()  # the stream closed: the command ended


def check_page(timeout_s: float) -> list[str]:
    """Steps 2-4: the capture page of the installed command, fetched over HTTP."""
    from mavcal.testing.vehicle import TestVehicle

    done: list[str] = []
    page = resources.files("mavcal.capture").joinpath("page")
    with TestVehicle(heartbeat_hz=5) as vehicle:
        cmd = _mavcal_command() + ["capture", "--connect", vehicle.gcs_device, "--ui", "--no-browser",
                                   "--duration", str(timeout_s)]
        env = dict(os.environ, PYTHONFAULTHANDLER="1")  # a hang is shown with its stacks (SIGABRT below)
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
        lines: list[str] = []
        seen = threading.Event()
        reader = threading.Thread(target=_read_lines, args=(proc.stderr, lines, seen), daemon=True)
        reader.start()
        try:
            seen.wait(timeout_s)
            m = next((m for m in map(_URL.search, lines) if m), None)
            if m is None or proc.poll() is not None:
                raise CheckFailed(f"mavcal capture --ui printed no page address in {timeout_s:.0f} s, or ended "
                                  f"(exit {proc.poll()}): {' | '.join(lines[-5:])}")
            port, token = int(m.group(1)), m.group(2)
            for path, name in ASSETS.items():
                status, body = _get(port, token, path)
                if status != 200:
                    raise CheckFailed(f"GET {path}: HTTP {status}: {body[:200]!r}")
                want = page.joinpath(name).read_bytes()
                if name == "index.html":  # the server puts the session's token into its links
                    want = want.replace(b"{{TOKEN}}", token.encode())
                if body != want:
                    raise CheckFailed(f"GET {path}: not the installed package's {name}")
                done.append(f"GET {path}: 200, {len(body)} bytes, the installed package's {name}")
            phase = _wait_capturing(port, token, proc, time.monotonic() + timeout_s)
            done.append(f"GET /state: the page follows the capture of the vehicle (phase {phase!r})")
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)  # a user's Ctrl-C
            try:
                proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGABRT)  # faulthandler prints every thread's stack
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                reader.join(5)
                stacks = "\n".join(lines[-60:])
                raise CheckFailed(f"mavcal capture did not end within {STOP_S:.0f} s of Ctrl-C; "
                                  f"its last output:\n{stacks}") from None
            finally:
                reader.join(5)
        if proc.returncode < 0 or proc.returncode == 70:  # killed, or an internal error (a traceback)
            raise CheckFailed(f"mavcal capture ended with {proc.returncode} on Ctrl-C: {' | '.join(lines[-5:])}")
        done.append(f"mavcal capture stopped by Ctrl-C: exit {proc.returncode}")
    return done


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mavcal.testing.installed", description=__doc__.splitlines()[0])
    p.add_argument("--not-under", type=Path, metavar="DIR",
                   help="the checkout: mavcal must not be imported from there (only from site-packages)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="seconds for the capture to serve its page (default 60)")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    try:
        pkg = check_location(args.not_under)
        print(f"ok: mavcal imported from {pkg}, with the capture page's files")
        for line in check_page(args.timeout):
            print(f"ok: {line}")
    except CheckFailed as exc:
        print(f"FAILED: {exc}")
        return 1
    print(f"ok: all checks passed in {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
