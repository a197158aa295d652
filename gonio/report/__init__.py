"""The HTML report: one self-contained page per run or per fit, checked in a real browser by the
tests.

============  ===============================================================================
module        what it holds
============  ===============================================================================
``page``      the page: its sections in order, the CSS, :func:`write_report` (a run) and
              :func:`write_fit_report` (any samples table and fit)
``sections``  the text sections: verdict box, value ± σ, calibration evidence, provenance
``maps``      the hemisphere: polar plots, hemisphere maps, sample map, albedo check
``plots``     matplotlib figures of a fit, as PNG data URIs
============  ===============================================================================
"""

from __future__ import annotations

from gonio.report.page import write_fit_report, write_report

__all__ = ["write_report", "write_fit_report"]
