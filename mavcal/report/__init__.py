"""What a person (or a script) looks at after a calibration.

* :mod:`mavcal.report.text`: the terminal summary, the parameter table and the outcome
  of a write to the vehicle (the same words from the CLI and the MAVProxy module);
* :mod:`mavcal.report.json`: the JSON report, written and loaded back;
* :mod:`mavcal.report.html`: the self-contained HTML report (figures in
  :mod:`mavcal.report.figures`, their numbers in :mod:`mavcal.report.numbers`).
"""
from mavcal.report.figures import FIGURE_NAMES
from mavcal.report.html import write_html
from mavcal.report.numbers import IntervalNumbers, corrected_after, interval_numbers
from mavcal.report.text import summary_text

__all__ = ["write_html", "summary_text", "interval_numbers", "IntervalNumbers", "corrected_after", "FIGURE_NAMES"]
