"""Typed report content: what a report says, with no HTML in it.

The forecast flow builds figures with :mod:`pipeline.report.figures` (PNG bytes), puts them with
tables (pandas DataFrames) into :class:`Section` objects and hands a :class:`ReportContent` to
:func:`pipeline.report.render.write_report`. Every string here is plain text: the template
escapes it, so data can never inject markup.

Page 1 is :class:`PageOne` (``ReportContent.page1``: the figure that carries the forecast, the
headline in one or two sentences, the forecast's table, the :class:`Notice` s of what the round
left out or held; :mod:`pipeline.report.page1`), then the headline (``ReportContent.headline``:
the published forecast's numbers in full, not a numbered section). Sections of the weekly report, in order (:class:`SectionKey`; titles in
``SECTION_TITLES``): the published 4-week forecast · its real-time backtest against the hub
baseline · the place's S/I/R series · β, γ and R_t over time · forward/backward state estimates ·
rollouts (7- and 28-day windows) · NF-seeded SMC · NLL table (paper Table 5 layout) ·
training/validation loss · appendix: provenance (from :class:`Provenance`, not a section).
Every band and interval is a 50 % or 90 % central interval.
"""
from __future__ import annotations

import datetime as dt
import enum
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

import pandas as pd

from pipeline.errors import FlowcastError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_FLAT_LIST = re.compile(r"\[\s+([^\[\]{}]*?)\s+\]")
_SENTENCE_END = re.compile(r"[.!?](?:\s|$)")


class ReportError(FlowcastError):
    """Report content that cannot be rendered (bad image, duplicate section, empty table...)."""


class SectionKey(enum.StrEnum):
    FORECAST = "forecast"
    BACKTEST = "backtest"
    SIR_SERIES = "sir-series"
    PARAMETERS = "parameters"
    STATE_ESTIMATES = "state-estimates"
    ROLLOUTS = "rollouts"
    SMC = "smc"
    NLL = "nll"
    TRAINING = "training"


SECTION_TITLES: Mapping[SectionKey, str] = MappingProxyType({
    SectionKey.FORECAST: "Forecast: the last 12 weeks and the next 4",
    SectionKey.BACKTEST: "Backtest: the published forecast against the hub baseline",
    SectionKey.SIR_SERIES: "San Francisco S/I/R series",
    SectionKey.PARAMETERS: "Transmission (β), recovery (γ) and R_t over time",
    SectionKey.STATE_ESTIMATES: "Forward and backward state estimates",
    SectionKey.ROLLOUTS: "Rollouts: 7- and 28-day windows",
    SectionKey.SMC: "NF-seeded particle filter (SMC)",
    SectionKey.NLL: "Negative log-likelihood by model variant",
    SectionKey.TRAINING: "Training and validation loss",
})


@dataclass(frozen=True)
class FigureItem:
    """A PNG figure with a caption (shown) and alt text (for screen readers and broken images).

    ``width="half"`` places two consecutive half figures side by side.
    """

    png: bytes
    caption: str
    alt: str
    width: Literal["full", "half"] = "full"

    def __post_init__(self) -> None:
        if not self.png.startswith(PNG_SIGNATURE):
            raise ReportError(f"figure {self.caption[:60]!r} is not a PNG image "
                              f"(first bytes {self.png[:8]!r})")
        if not self.alt.strip():
            raise ReportError(f"figure {self.caption[:60]!r} has no alt text")
        if self.width not in ("full", "half"):
            raise ReportError(f"figure width must be 'full' or 'half', got {self.width!r}")


@dataclass(frozen=True, eq=False)
class TableItem:
    """A table with a caption. ``frame`` may have a two-level column index (e.g. model × S/I/R
    or value × paper/ours); its index is shown as row labels.

    A two-level row index shows as two label columns, equal neighbouring labels merged.

    ``decimals``: digits after the point for floats. ``highlight``: bold the best value of each
    row (``"row-min"``, as the paper's tables do for the lowest NLL/KL) or of each column
    (``"col-min"``), or nothing. ``css``: an extra class for the table (e.g. ``headline``).
    """

    frame: pd.DataFrame
    caption: str
    decimals: int = 3
    highlight: Literal["row-min", "row-max", "col-min"] | None = None
    note: str = ""
    css: str = ""

    def __post_init__(self) -> None:
        if self.frame.empty:
            raise ReportError(f"table {self.caption[:60]!r} is empty")
        if self.frame.columns.nlevels > 2 or self.frame.index.nlevels > 2:
            raise ReportError(f"table {self.caption[:60]!r} has {self.frame.columns.nlevels} "
                              f"column and {self.frame.index.nlevels} row levels; at most 2 "
                              "each are supported")
        # a private copy: later changes to the caller's frame must not change the report
        object.__setattr__(self, "frame", self.frame.copy(deep=True))


@dataclass(frozen=True)
class Section:
    """One titled part of a report: alerts (diagnostics that signal trouble, in words), an
    optional intro paragraph, then figures and tables. ``new_page``: starts a PDF page (False
    lets a short section follow the previous one instead of leaving a page half empty)."""

    key: str
    title: str
    items: tuple[FigureItem | TableItem, ...]
    intro: str = ""
    alerts: tuple[str, ...] = ()
    new_page: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "items", tuple(self.items))
        object.__setattr__(self, "alerts", tuple(self.alerts))
        bad = [type(i).__name__ for i in self.items if not isinstance(i, (FigureItem, TableItem))]
        if bad:
            raise ReportError(f"section {self.key!r} holds unsupported items {bad}")

    @classmethod
    def weekly(cls, key: SectionKey, items: Sequence[FigureItem | TableItem],
               intro: str = "", alerts: Sequence[str] = (), new_page: bool = True,
               title: str | None = None) -> Section:
        """A section of the weekly report with its canonical anchor and title (``title``
        replaces the canonical one, e.g. to name the place)."""
        return cls(key=str(key), title=title or SECTION_TITLES[key], items=tuple(items),
                   intro=intro, alerts=tuple(alerts), new_page=new_page)


class NoticeKind(enum.StrEnum):
    """Why a notice is on page 1."""

    LEFT_OUT = "left out"       # a place, member or target this round went without
    HELD = "held"               # data held for review, or older than the round wants
    NOTE = "note"               # anything else the reader must know before the numbers


@dataclass(frozen=True)
class Notice:
    """One thing this round left out or held, said in words on page 1."""

    kind: NoticeKind
    text: str

    def __post_init__(self) -> None:
        if not self.text.strip():
            raise ReportError("a page-1 notice has no text")
        object.__setattr__(self, "kind", NoticeKind(self.kind))


@dataclass(frozen=True)
class PageOne:
    """Page 1: ``figures`` (the fan chart first; a hub round's map beside it), the
    ``headline`` (one or two sentences), the forecast ``table`` and the ``notices``."""

    figures: tuple[FigureItem, ...]
    headline: str
    table: TableItem
    notices: tuple[Notice, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "figures", tuple(self.figures))
        object.__setattr__(self, "notices", tuple(self.notices))
        if not self.figures:
            raise ReportError("page 1 needs the figure that carries the forecast")
        sentences = len(_SENTENCE_END.findall(self.headline.strip()))
        if not 1 <= sentences <= 2:
            raise ReportError(f"page 1's headline must be one or two sentences, got "
                              f"{sentences}: {self.headline[:120]!r}")


def _freeze(mapping: Mapping[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(dict(mapping))


@dataclass(frozen=True)
class Provenance:
    """Where the numbers come from: enough to reproduce the run."""

    package_version: str
    versions: Mapping[str, str] = field(default_factory=dict)     # python, torch, numpy, ...
    config: Mapping[str, Any] = field(default_factory=dict)       # the run's typed config, as dict
    data_sha256: str = ""
    checkpoint_sha256: str = ""
    seed: int | None = None
    extra: Mapping[str, str] = field(default_factory=dict)        # e.g. run id, command line

    def __post_init__(self) -> None:
        for name in ("versions", "config", "extra"):
            object.__setattr__(self, name, _freeze(getattr(self, name)))

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) pairs in display order."""
        rows = [("flowcast version", self.package_version)]
        rows += [(f"{name} version", str(v)) for name, v in sorted(self.versions.items())]
        rows += [("data sha256", self.data_sha256 or "—"),
                 ("model checkpoint sha256", self.checkpoint_sha256 or "—"),
                 ("seed", "—" if self.seed is None else str(self.seed))]
        rows += [(k, str(v)) for k, v in self.extra.items()]
        return rows

    def config_json(self) -> str:
        text = json.dumps(dict(self.config), indent=2, sort_keys=True, default=str)
        # lists of plain values on one line: the appendix is half as long
        return _FLAT_LIST.sub(lambda m: "[" + " ".join(m.group(1).split()) + "]", text)


@dataclass(frozen=True)
class ReportContent:
    """Everything one report shows. Build it in the flow; render it with ``render_html``."""

    title: str
    reference_date: dt.date
    data_vintage: str                     # e.g. "DataSF export, data as of 2022-03-21 04:30"
    sections: tuple[Section, ...]
    provenance: Provenance
    warnings: tuple[str, ...] = ()        # e.g. "Data are stale by 9 days (fetch failed)."
    summary: str = ""                     # a short lead paragraph under the title
    generated_at: dt.datetime | None = None
    headline: Section | None = None       # the forecast's numbers, before any section
    page1: PageOne | None = None          # page 1: the figure, headline, table, notices
    kicker: str = "flowcast weekly report"   # the line above the title: which report this is

    def __post_init__(self) -> None:
        object.__setattr__(self, "sections", tuple(self.sections))
        object.__setattr__(self, "warnings", tuple(self.warnings))
        keys = [s.key for s in self.sections]
        duplicates = sorted({k for k in keys if keys.count(k) > 1})
        if duplicates:
            raise ReportError(f"duplicate section keys {duplicates}")
        if not isinstance(self.reference_date, dt.date):
            raise ReportError(f"reference_date must be a date, got {self.reference_date!r}")

    @property
    def checks(self) -> tuple[tuple[str, str, str], ...]:
        """(section key, section title, alert) for every section's alert: page 1 lists them."""
        return tuple((s.key, s.title, a) for s in self.sections for a in s.alerts)


def stale_data_warning(latest_data_date: dt.date, as_of: dt.date, tolerance_days: int = 7,
                       as_of_label: str = "the run date") -> str | None:
    """The warning text when the newest data point is more than ``tolerance_days`` older than
    ``as_of`` (e.g. the day the run happened), else None."""
    age = (as_of - latest_data_date).days
    if age <= tolerance_days:
        return None
    return (f"Data are stale: the newest observation is from {latest_data_date.isoformat()}, "
            f"{age} days before {as_of_label} ({as_of.isoformat()}).")


def nll_table(nll: Mapping[tuple[str, str], float],
              variants: Sequence[str] = ("Transformer", "Transformer + KE", "Mamba-SSM"),
              directions: Sequence[str] = ("fw", "bw")) -> pd.DataFrame:
    """The paper's Table 5 layout: rows fw/bw, one column per model variant.

    ``nll[(direction, variant)]`` = mean NLL aggregated over S, I, R; missing cells are NaN
    (shown as "—").
    """
    unknown = sorted({k for k in nll} - {(d, v) for d in directions for v in variants})
    if unknown:
        raise ReportError(f"NLL entries {unknown} are not among directions {list(directions)} "
                          f"× variants {list(variants)}")
    data = [[nll.get((d, v), float("nan")) for v in variants] for d in directions]
    frame = pd.DataFrame(data, index=pd.Index(list(directions), name="direction"),
                         columns=pd.Index(list(variants), name="model"))
    return frame


def paper_vs_ours(paper: pd.DataFrame, ours: pd.DataFrame) -> pd.DataFrame:
    """Interleave two same-shaped tables: columns (column, "paper") and (column, "ours").

    Rows and columns of ``ours`` must match ``paper``'s (missing ours → NaN, shown "—").
    """
    extra = [c for c in ours.columns if c not in paper.columns]
    if extra:
        raise ReportError(f"our table has columns {extra} that the paper's table lacks")
    ours = ours.reindex(index=paper.index, columns=paper.columns)
    pieces: dict[tuple[str, str], pd.Series] = {}
    for column in paper.columns:
        label = column if isinstance(column, tuple) else (column,)
        pieces[(" ".join(map(str, label)), "paper")] = paper[column]
        pieces[(" ".join(map(str, label)), "ours")] = ours[column]
    frame = pd.DataFrame(pieces, index=paper.index)
    frame.columns = pd.MultiIndex.from_tuples(list(pieces))
    return frame
