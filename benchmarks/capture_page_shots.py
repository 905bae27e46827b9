"""Screenshots of the live capture page for the documentation, from the real page against the
real ArduPilot SITL (not drawn by hand).

A SITL copter (``mavcal.testing.sitl``: private network namespace, real time) with random sensor
errors (``InjectedErrors.random(SEED, mag_orient=6)``) and a wrong calibration in force;
``mavcal capture --connect ... --ui --no-browser`` runs in its namespace; headless chromium
(``mavcal.testing.browser``, started in the same namespace) opens the page the CLI prints, while
the scripted hand of ``mavcal.testing.sitl_hand`` holds each pose the capture advises. Four
moments are saved as PNG: ``capture-start`` (the first advice), ``capture-mid`` (seven or more poses
counted, the advised pose matched and being held), ``capture-verdict`` (the verdicts and the
parameter table) and ``capture-written`` (after Write, confirmed in the page's dialog: the
writer's outcome). The run fails, saving nothing further, if a moment does not come.

    python benchmarks/capture_page_shots.py            # -> benchmarks/out/capture_page_shots/ (untracked)
    python benchmarks/capture_page_shots.py --save     # -> docs/img/ (the images the documentation shows)
    python benchmarks/capture_page_shots.py --px4 --seed 4 --save   # the same against PX4 SITL: docs/img/px4-*.png

Needs what the SITL tests need (Linux, root for the namespace, ``../shared/sitl/arducopter``)
and chromium + chromium-driver + selenium (the ``[test]`` extra). About 2 minutes.
"""
from __future__ import annotations

import argparse
import contextlib
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mavcal.testing.browser import headless_chromium, missing, page_text, wait_for
from mavcal.testing.sitl import InjectedErrors, SitlVehicle, unavailable_reason
from mavcal.testing.sitl_hand import AdviceHand, StatusLines

HERE = Path(__file__).resolve().parent
DOCS_IMG = HERE.parent / "docs" / "img"
SEED = 101
WIDTH, HEIGHT = 1280, 860
URL = re.compile(r"capture page: (http://127\.0\.0\.1:\d+/\?t=\S+)")


def _shoot(drv: Any, out: Path, prefix: str, name: str, full_height: bool = False) -> Path:
    """The viewport as ``out/<prefix><name>.png`` (``full_height``: the window grown to the whole page first)."""
    if full_height:
        h = int(drv.execute_script("return document.documentElement.scrollHeight"))
        drv.set_window_size(WIDTH, min(max(h + 40, HEIGHT), 1300))
        time.sleep(0.5)
    path = out / f"{prefix}{name}.png"
    drv.save_screenshot(str(path))
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)", flush=True)
    return path


def _url(status: StatusLines, proc: subprocess.Popen) -> str:
    def find() -> str | None:
        m = URL.search(status.text())
        return m.group(1) if m else None
    return wait_for("the page's address on stderr", lambda: find() or proc.poll() is not None, 90,
                    show=lambda: status.text()[-800:]) and (find() or "")


def _drive(drv: Any, url: str, status: StatusLines, hand: AdviceHand, out: Path, prefix: str) -> None:
    """Open the page, take the four screenshots, Write and confirm."""
    drv.get(url)
    wait_for("the first advice and the live attitude", lambda: drv.execute_script(
        "return document.querySelectorAll('#scene-live polygon').length") > 3
        and page_text(drv, "pose-words").strip() != "", 120, show=lambda: page_text(drv, "instruction"))
    time.sleep(1.0)  # the ring and the live drawing settle
    _shoot(drv, out, prefix, "capture-start")
    hand.start()

    def mid() -> bool:
        n = status()[0]
        matched = drv.execute_script("return document.getElementById('live-figure').classList.contains('match')")
        holding = "Still" in page_text(drv, "hold-text")
        fitted = drv.execute_script("return document.querySelectorAll('#bars .bar:not(.none)').length") > 0
        return n >= 7 and bool(matched) and holding and fitted and not status()[2]
    wait_for("a mid-capture view (7+ poses, the advised pose matched and held)", mid, 240, poll_s=0.05,
             show=lambda: status.text()[-600:])
    _shoot(drv, out, prefix, "capture-mid")

    wait_for("the verdict", lambda: drv.execute_script(
        "return !document.getElementById('result').hidden && !document.getElementById('write').disabled"), 300,
        show=lambda: status.text()[-600:])
    hand.stop()
    time.sleep(0.5)
    _shoot(drv, out, prefix, "capture-verdict", full_height=True)

    drv.find_element("id", "write").click()
    wait_for("the confirmation dialog", lambda: drv.execute_script("return document.getElementById('confirm').open"), 10)
    drv.find_element("id", "confirm-yes").click()
    wait_for("the write's outcome", lambda: "Written" in page_text(drv, "write-outcome"), 120,
             show=lambda: page_text(drv, "write-outcome"))
    drv.execute_script("document.getElementById('write-outcome').scrollIntoView({block: 'center'})")
    drv.set_window_size(WIDTH, HEIGHT)
    time.sleep(0.5)
    _shoot(drv, out, prefix, "capture-written")


def _drive_reach(drv: Any, url: str, status: StatusLines, hand: AdviceHand, out: Path, prefix: str) -> None:
    """--max-tilt: one screenshot, "capture-reach", of the page advising a tilted pose with its
    raised edge on a block (a vehicle that cannot be turned over), once a few poses are held."""
    drv.get(url)
    wait_for("the first advice", lambda: page_text(drv, "pose-words").strip() != "", 120,
             show=lambda: page_text(drv, "instruction"))
    hand.start()

    def tilted() -> bool:
        block = drv.execute_script("return document.querySelectorAll('#scene-target [data-block]').length") > 0
        return status()[0] >= 4 and bool(block) and not status()[2]
    wait_for("a tilted pose on its block advised (4+ poses held)", tilted, 240, poll_s=0.05,
             show=lambda: status.text()[-600:])
    time.sleep(1.0)
    _shoot(drv, out, prefix, "capture-reach")


@contextlib.contextmanager
def _vehicle(seed: int, px4: bool):
    """ArduPilot SITL with random injected errors, or (``px4``) PX4 SITL posed with random sensor errors."""
    if px4:
        from mavcal.testing.px4_poser import posed_px4

        with posed_px4(seed) as (posed, _):
            yield posed
    else:
        with SitlVehicle(InjectedErrors.random(seed, mag_orient=6)) as sitl:
            yield sitl


def run(out: Path, seed: int, max_tilt: float | None = None, px4: bool = False) -> int:
    with _vehicle(seed, px4) as sitl, tempfile.TemporaryDirectory(prefix="capture-shots-") as tmp:
        status = StatusLines()
        p = sitl.popen([sys.executable, "-m", "mavcal", "capture", "--connect", sitl.tool_device, "--ui",
                        "--no-browser", "--json", str(Path(tmp) / "run.json"),
                        "--backup", str(Path(tmp) / "backup.param")]
                       + ([] if max_tilt is None else ["--max-tilt", f"{max_tilt:g}"]),
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        reader = status.follow(p.stderr)
        hand = AdviceHand(sitl, status, seed=seed)
        try:
            url = _url(status, p)
            if not url:
                print(f"capture_page_shots: the capture ended before serving its page:\n{status.text()[-1500:]}",
                      file=sys.stderr)
                return 1
            with sitl.netns(), headless_chromium(WIDTH, HEIGHT) as drv:  # the browser in the vehicle's namespace
                (_drive if max_tilt is None else _drive_reach)(drv, url, status, hand, out, "px4-" if px4 else "")
            if max_tilt is not None:  # the screenshot is taken: nothing is written
                hand.stop()
                p.send_signal(signal.SIGINT)
            rc = p.wait(timeout=60)
        finally:
            hand.stop()
            if p.poll() is None:
                p.kill()
            reader.join(timeout=10)
        print(f"capture exited {rc}; poses held: {len(hand.poses)}")
        return 0 if rc in (0, 7) or (max_tilt is not None and rc in (4, 130, -2)) else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=SEED, help="the SITL's injected errors and the hand's coin")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--save", action="store_true", help=f"write into {DOCS_IMG.relative_to(HERE.parent)}/ (tracked)")
    g.add_argument("--out", type=Path, metavar="DIR", help="write into DIR")
    ap.add_argument("--max-tilt", type=float, metavar="DEG",
                    help="a capture within reach (capture --max-tilt DEG): the one screenshot capture-reach, no write")
    ap.add_argument("--px4", action="store_true",
                    help="against PX4 SITL (../shared/px4, posed by mavcal's test poser): the images named px4-*.png")
    args = ap.parse_args(argv)
    if args.px4:
        from mavcal.testing.px4_sitl import px4_unavailable_reason

        reason = px4_unavailable_reason()
    else:
        reason = unavailable_reason()
    reason = reason or (f"{', '.join(missing())} not installed" if missing() else None)
    if reason is not None:
        print(f"capture_page_shots: {reason}", file=sys.stderr)
        return 2
    from bench_output import resolve

    out = DOCS_IMG if args.save else resolve(False, args.out)
    if out == resolve(False, None):
        out = out / "capture_page_shots"
    out.mkdir(parents=True, exist_ok=True)
    return run(out, args.seed, args.max_tilt, args.px4)


if __name__ == "__main__":
    sys.exit(main())
