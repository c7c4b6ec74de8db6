"""Reports: typed content (``content``), figure builders (``figures``), HTML/PDF (``render``).

The forecast flow passes data only: arrays → ``figures.*`` → PNG bytes → ``FigureItem``;
DataFrames → ``TableItem``; both into ``Section``s of a ``ReportContent``; then
``write_report(content, out_dir)``.
"""
from pipeline.report.content import (SECTION_TITLES, FigureItem, Provenance, ReportContent,
                                     ReportError, Section, SectionKey, TableItem, nll_table,
                                     paper_vs_ours, stale_data_warning)
from pipeline.report.render import (ReportFiles, render_html, render_pdf, render_reproduction,
                                    write_report, write_reproduction)



def build_forecast_report(results, out_dir):  # type: ignore[no-untyped-def]
    """Weekly report of a ``pipeline.forecast.steps.ForecastResults`` (see ``report.weekly``)."""
    from pipeline.report.weekly import build_forecast_report as build

    return build(results, out_dir)


__all__ = [
    "build_forecast_report",
    "SECTION_TITLES", "FigureItem", "Provenance", "ReportContent", "ReportError", "ReportFiles",
    "Section", "SectionKey", "TableItem", "nll_table", "paper_vs_ours", "render_html",
    "render_pdf", "render_reproduction", "stale_data_warning", "write_report",
    "write_reproduction",
]
