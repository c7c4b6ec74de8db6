"""Reports: typed content (``content``), figure builders (``figures``), HTML/PDF (``render``).

The forecast flow passes data only: arrays → ``figures.*`` → PNG bytes → ``FigureItem``;
DataFrames → ``TableItem``; both into ``Section``s of a ``ReportContent``; then
``write_report(content, out_dir)``.
"""
from pipeline.report.content import (SECTION_TITLES, FigureItem, Notice, NoticeKind, PageOne,
                                     Provenance, ReportContent, ReportError, Section, SectionKey,
                                     TableItem, nll_table, paper_vs_ours, stale_data_warning)
from pipeline.report.render import (ReportFiles, render_html, render_pdf, render_reproduction,
                                    write_report, write_reproduction)

# The weekly forecast's report is pipeline.forecast.report: it reads the weekly run's results
# (pipeline.forecast.results), a layer above this generic one.

__all__ = [
    "SECTION_TITLES", "FigureItem", "Notice", "NoticeKind", "PageOne", "Provenance", "ReportContent", "ReportError", "ReportFiles",
    "Section", "SectionKey", "TableItem", "nll_table", "paper_vs_ours", "render_html",
    "render_pdf", "render_reproduction", "stale_data_warning", "write_report",
    "write_reproduction",
]
