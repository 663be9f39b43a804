"""Figures (matplotlib) and HTML: the surface report and the diagnosis report."""

from ._diagnosis import diagnose_with_report
from ._diagnosis import write_report as write_diagnosis_report
from ._report import write_report

__all__ = ["diagnose_with_report", "write_diagnosis_report", "write_report"]
