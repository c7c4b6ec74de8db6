"""Render report content to one self-contained HTML page and the same content as PDF.

* HTML: Jinja2 with autoescaping; the stylesheet is inlined in a ``<style>`` element and every
  image is a ``data:image/png;base64`` URI, so the page loads nothing from anywhere (no fonts,
  scripts, links or images by URL) and can be mailed or archived as one file.
* PDF: WeasyPrint renders the *same* HTML; the stylesheet's ``@media print`` part gives A4
  pages, a page break before each section, running headers and "page N of M" footers.
  WeasyPrint's URL fetcher is replaced by one that only serves ``data:`` URIs, so a stray
  external reference fails loudly instead of causing a network request.
* ``write_report`` renders both in memory first and only then replaces the files atomically
  (``pipeline.io``): a rendering failure leaves the previous report untouched.
"""
from __future__ import annotations

import base64
import functools
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import jinja2
import markupsafe
import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.forked import ChildBuild, start_in_child
from pipeline.io import atomic_write_bytes, atomic_write_text, sha256_bytes
from pipeline.report.content import (FigureItem, PageOne, Provenance, ReportContent, ReportError,
                                     Section, TableItem)

HTML_NAME = "report.html"
PDF_NAME = "report.pdf"
_TEMPLATES = "templates"


@dataclass(frozen=True)
class ReportFiles:
    html_path: Path
    pdf_path: Path
    n_pages: int
    html_sha256: str
    pdf_sha256: str


# ----------------------------------------------------------------------------- environment

def _template_dir() -> Path:
    return Path(str(resources.files("pipeline.report") / _TEMPLATES))


def _environment() -> jinja2.Environment:
    return jinja2.Environment(loader=jinja2.FileSystemLoader(_template_dir()),
                              autoescape=True, undefined=jinja2.StrictUndefined,
                              trim_blocks=False, lstrip_blocks=False)


def _stylesheet() -> markupsafe.Markup:
    """The stylesheet, marked safe for the <style> element (it is our file, not user data)."""
    css = (_template_dir() / "report.css").read_text(encoding="utf-8")
    if "</" in css:
        raise ReportError("report.css must not contain '</' (it would close the <style> element)")
    return markupsafe.Markup(css)


# ----------------------------------------------------------------------------- view models

def _figure_view(fig: FigureItem) -> dict[str, str]:
    data = base64.b64encode(fig.png).decode("ascii")
    return {"src": f"data:image/png;base64,{data}", "alt": fig.alt, "caption": fig.caption,
            "width": fig.width}


def _label(value: Any) -> str:
    if isinstance(value, tuple):
        return " / ".join(_label(v) for v in value)
    if isinstance(value, pd.Timestamp):
        return value.date().isoformat() if value == value.normalize() else value.isoformat()
    return str(value)


def _header_rows(columns: pd.Index) -> list[list[dict[str, Any]]]:
    """One header row per column level; equal neighbouring labels merge into one colspan."""
    rows = []
    for level in range(columns.nlevels):
        labels = columns.get_level_values(level)
        # a cell spans while this level's label and every higher level's label stay the same
        keys = [tuple(columns.get_level_values(k)[i] for k in range(level + 1))
                for i in range(len(columns))]
        row: list[dict[str, Any]] = []
        for i, key in enumerate(keys):
            if row and keys[i - 1] == key:
                row[-1]["colspan"] += 1
            else:
                row.append({"text": _label(labels[i]), "colspan": 1})
        rows.append(row)
    return rows


def _format_cell(value: Any, decimals: int) -> tuple[str, str]:
    if value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA:
        return "—", "missing"
    if isinstance(value, (bool, np.bool_)):
        return ("yes" if value else "no"), "text"
    if isinstance(value, (int, np.integer)):
        return f"{int(value):,}", ""
    if isinstance(value, (float, np.floating)):
        if math.isinf(value):
            return ("∞" if value > 0 else "−∞"), ""
        text = f"{float(value):.{decimals}f}"
        return text.replace("-", "−"), ""
    return _label(value), "text"


def _best_mask(frame: pd.DataFrame, highlight: str | None) -> np.ndarray:
    mask = np.zeros(frame.shape, dtype=bool)
    if highlight is None:
        return mask
    numeric = frame.apply(pd.to_numeric, errors="coerce").to_numpy(dtype=np.float64)
    finite = np.isfinite(numeric)
    if highlight == "col-min":
        best_col = np.where(finite, numeric, np.inf).min(axis=0)
        return finite & (numeric == best_col[None, :])
    fill = np.inf if highlight == "row-min" else -np.inf
    filled = np.where(finite, numeric, fill)
    best = filled.min(axis=1) if highlight == "row-min" else filled.max(axis=1)
    mask = finite & (filled == best[:, None])
    return mask


def _row_labels(index: pd.Index) -> list[list[dict[str, Any]]]:
    """Label cells per row, one per index level; a label equal to the one above (and with the
    same higher levels) is merged into it (``rowspan``), and its row gets no cell there."""
    keys = [label if isinstance(label, tuple) else (label,) for label in index]
    rows: list[list[dict[str, Any]]] = [[] for _ in keys]
    for level in range(index.nlevels):
        owner: dict[str, Any] | None = None
        for r, key in enumerate(keys):
            if (level < index.nlevels - 1 and owner is not None
                    and keys[r - 1][:level + 1] == key[:level + 1]):
                owner["rowspan"] += 1
                continue
            owner = {"text": _label(key[level]), "rowspan": 1}
            rows[r].append(owner)
    return rows


def _table_view(table: TableItem) -> dict[str, Any]:
    frame = table.frame
    best = _best_mask(frame, table.highlight)
    rows = []
    labels = _row_labels(frame.index)
    for r, values in enumerate(frame.itertuples(index=False)):
        cells = []
        for c, value in enumerate(values):
            text, css = _format_cell(value, table.decimals)
            if best[r, c]:
                css = (css + " best").strip()
            cells.append({"text": text, "css": css})
        rows.append({"labels": labels[r], "cells": cells})
    index_names = [str(n) if n is not None else "" for n in frame.index.names]
    return {"header_rows": _header_rows(frame.columns), "rows": rows,
            "index_names": index_names, "caption": table.caption, "note": table.note,
            "css": table.css}


def _blocks(items: Sequence[FigureItem | TableItem]) -> list[dict[str, Any]]:
    """Group consecutive half-width figures in pairs; everything else is its own block."""
    blocks: list[dict[str, Any]] = []
    for item in items:
        if isinstance(item, TableItem):
            blocks.append({"kind": "table", "table": _table_view(item)})
        elif item.width == "half":
            last = blocks[-1] if blocks else None
            if last and last["kind"] == "figure-row" and len(last["figures"]) < 2:
                last["figures"].append(_figure_view(item))
            else:
                blocks.append({"kind": "figure-row", "figures": [_figure_view(item)]})
        else:
            blocks.append({"kind": "figure", "figure": _figure_view(item)})
    return blocks


def _section_view(section: Section) -> dict[str, Any]:
    return {"key": section.key, "title": section.title, "intro": section.intro,
            "alerts": section.alerts, "new_page": section.new_page,
            "blocks": _blocks(section.items)}


def _page_one_view(page: PageOne) -> dict[str, Any]:
    return {"blocks": _blocks(page.figures), "headline": page.headline,
            "table": _table_view(page.table),
            "notices": [{"kind": str(n.kind), "text": n.text} for n in page.notices]}


def _provenance_view(p: Provenance) -> dict[str, Any]:
    return {"rows": p.rows(), "config_json": p.config_json() if p.config else ""}


# ----------------------------------------------------------------------------- public API

def render_html(content: ReportContent) -> str:
    """The weekly report as one self-contained HTML page (deterministic for equal content)."""
    template = _environment().get_template("report.html.j2")
    generated = content.generated_at.isoformat(timespec="minutes") if content.generated_at else ""
    return template.render(
        title=content.title, kicker=content.kicker, version=__version__, css=_stylesheet(),
        reference_date=content.reference_date.isoformat(), data_vintage=content.data_vintage,
        generated_at=generated, warnings=content.warnings, summary=content.summary,
        headline=_section_view(content.headline) if content.headline else None,
        page1=_page_one_view(content.page1) if content.page1 else None,
        checks=content.checks, sections=[_section_view(s) for s in content.sections],
        provenance=_provenance_view(content.provenance))


def _refuse_external(url: str) -> None:
    if not url.startswith("data:"):
        raise ReportError(f"report references an external resource {url[:120]!r}; reports "
                          "must be self-contained (data: URIs only)")


def _data_only_fetcher() -> Any:
    """A WeasyPrint URL fetcher that serves ``data:`` URIs and stops rendering on anything else."""
    import weasyprint.urls as wurls

    if hasattr(wurls, "URLFetcher"):                       # WeasyPrint ≥ 68: a class
        class DataOnlyFetcher(wurls.URLFetcher):
            def fetch(self, url: str, headers: Any = None) -> Any:
                _refuse_external(url)
                return super().fetch(url, headers)

        return DataOnlyFetcher(allowed_protocols=("data",), fail_on_errors=True)

    def fetch(url: str, *args: Any, **kwargs: Any) -> Any:  # older WeasyPrint: a function
        _refuse_external(url)
        # WeasyPrint < 68 only: the version pyright sees (>= 68) no longer has it.
        fetcher = wurls.default_url_fetcher  # pyright: ignore[reportAttributeAccessIssue]
        return fetcher(url, *args, **kwargs)
    return fetch


def preload_pdf_renderer() -> None:
    """Import WeasyPrint (Pango, fonts: about a second) ahead of the first PDF, e.g. in a thread
    while a run waits for something else."""
    import weasyprint  # noqa: F401
    import weasyprint.urls  # noqa: F401


def pdf_bytes(html: str) -> tuple[bytes, int]:
    """Render HTML to PDF bytes with WeasyPrint; returns (pdf, number of pages).

    Raises ``ReportError`` if the HTML references anything but ``data:`` URIs.
    """
    import weasyprint  # heavy import (Pango, fonts): only when a PDF is wanted
    from weasyprint.urls import FatalURLFetchingError

    try:
        document = weasyprint.HTML(string=html, url_fetcher=_data_only_fetcher()).render()
    except FatalURLFetchingError as exc:
        raise ReportError(f"{exc}: {exc.__cause__}") from exc
    pdf = document.write_pdf()
    assert pdf is not None  # write_pdf returns the bytes when given no target
    return pdf, len(document.pages)


def render_pdf(html: str, path: str | os.PathLike[str]) -> int:
    """Render ``html`` to a PDF at ``path`` (atomic write); returns the number of pages."""
    data, n_pages = pdf_bytes(html)
    atomic_write_bytes(path, data)
    return n_pages


def _write_pair(html: str, out_dir: str | os.PathLike[str], stem: str) -> ReportFiles:
    # everything rendered before anything is replaced
    return _write_rendered(html, pdf_bytes(html), out_dir, stem)


def _write_rendered(html: str, rendered_pdf: tuple[bytes, int], out_dir: str | os.PathLike[str],
                    stem: str) -> ReportFiles:
    out = Path(out_dir)
    pdf, n_pages = rendered_pdf
    html_path, pdf_path = out / f"{stem}.html", out / f"{stem}.pdf"
    atomic_write_bytes(pdf_path, pdf)
    atomic_write_text(html_path, html)
    return ReportFiles(html_path=html_path, pdf_path=pdf_path, n_pages=n_pages,
                       html_sha256=sha256_bytes(html.encode("utf-8")),
                       pdf_sha256=sha256_bytes(pdf))


def write_report(content: ReportContent, out_dir: str | os.PathLike[str]) -> ReportFiles:
    """Write ``report.html`` and ``report.pdf`` into ``out_dir``.

    Both are rendered in memory first; then each file is replaced atomically, so a failure
    while rendering leaves any previous report in ``out_dir`` intact.
    """
    return _write_pair(render_html(content), out_dir, "report")


@dataclass(frozen=True, eq=False)
class RenderingReport:
    """A report's HTML and its PDF under way in a forked child (:func:`start_report`)."""

    html: str
    pdf: ChildBuild[tuple[bytes, int]]

    def write(self, out_dir: str | os.PathLike[str], stem: str = "report") -> ReportFiles:
        """Wait for the PDF, then write both as :func:`write_report` does."""
        return _write_rendered(self.html, self.pdf.result(), out_dir, stem)


def start_report(content: ReportContent) -> RenderingReport:
    """The report's HTML, and its PDF laid out by WeasyPrint in a forked child
    (:mod:`pipeline.forked`: the same bytes as here): seconds of layout while this process goes
    on, e.g. writing a run's tables. :meth:`RenderingReport.write` writes both files."""
    html = render_html(content)
    return RenderingReport(html, start_in_child(functools.partial(pdf_bytes, html)))


def _reproduction_sections(tables: Sequence[tuple[str, pd.DataFrame] | TableItem],
                           figures: Sequence[FigureItem]) -> list[Section]:
    sections = []
    for k, entry in enumerate(tables):
        if isinstance(entry, TableItem):
            item, title = entry, entry.caption
        else:
            title, frame = entry
            item = TableItem(frame=frame, caption=title)
        sections.append(Section(key=f"table-{k + 1}", title=title, items=(item,)))
    if figures:
        sections.append(Section(key="figures", title="Confidence regions",
                                items=tuple(figures)))
    return sections


def render_reproduction(tables: Sequence[tuple[str, pd.DataFrame] | TableItem],
                        figures: Sequence[FigureItem] = (), *,
                        title: str = "Reproduction of the paper's tables",
                        intro: str = "", provenance: Provenance | None = None) -> str:
    """The paper-reproduction report as HTML: one section per table (e.g. KL divergence with
    the paper's numbers beside ours, see ``content.paper_vs_ours``), then the figures."""
    if not tables and not figures:
        raise ReportError("a reproduction report needs at least one table or figure")
    template = _environment().get_template("reproduction.html.j2")
    sections = _reproduction_sections(tables, figures)
    return template.render(title=title, version=__version__, css=_stylesheet(), intro=intro,
                           sections=[_section_view(s) for s in sections],
                           provenance=_provenance_view(provenance) if provenance else None)


def write_reproduction(tables: Sequence[tuple[str, pd.DataFrame] | TableItem],
                       figures: Sequence[FigureItem], out_dir: str | os.PathLike[str], *,
                       title: str = "Reproduction of the paper's tables", intro: str = "",
                       provenance: Provenance | None = None) -> ReportFiles:
    """Write ``reproduction.html`` and ``reproduction.pdf`` (same guarantees as write_report)."""
    html = render_reproduction(tables, figures, title=title, intro=intro, provenance=provenance)
    return _write_pair(html, out_dir, "reproduction")
