"""report.html: tables, interactive plots and test-view viewers in one page (see ``page``)."""

from reports.html.page import html_report

__all__ = ["html_report"]
