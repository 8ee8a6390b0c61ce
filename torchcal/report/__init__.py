"""Reports: error statistics, JSON / Markdown files and plots for calibrations, loops, fleets and
pose plans. :func:`write_report` writes any driver's result; the results themselves are records."""
from torchcal.report.write import report_json, write_report

__all__ = ["write_report", "report_json"]
