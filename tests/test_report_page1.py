"""Issue 41: page 1 of every report, the hub round's map, tables that fit the PDF page, the hub
track record against the hub's baseline as the hub scores it, the HTML in headless Chromium.

A real tiny hub round (the NHSN/NSSP releases since 2025-09-10 of ``../shared/data/nhsn``: three
rounds, imported into a temporary FLOWCAST_DATA_DIR, run offline, seconds) is reported and its
rendered PDF and HTML measured. The checkers themselves are shown to find what they look for
(a table cut at the margin, a console error), so that a zero from them means something.
"""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.report.content import (FigureItem, Notice, NoticeKind, PageOne, Provenance,
                                     ReportContent, ReportError, TableItem)
from pipeline.report.hub_figures import TILE_GRID, tile_map_figure
from pipeline.report.page1 import MAX_WORDS, fan_chart_figure, word_count
from pipeline.report.render import render_html, write_report
from tests.browser import (browser_check, missing_tool_reason, overflowing_text_boxes,
                           pdf_page_images, pdf_page_words)

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
ADMISSIONS = "wk inc covid hosp"


def _tools() -> None:
    for tool in ("pdftotext", "pdfimages", "chromium"):
        if reason := missing_tool_reason(tool):
            pytest.skip(reason)


# ----------------------------------------------------------------------------- units

def test_the_tile_grid_holds_every_state_dc_and_puerto_rico_once():
    from pipeline.data.hub.locations import HUB_LOCATIONS, US

    places = {h.abbreviation for h in HUB_LOCATIONS if h.location != US}
    assert set(TILE_GRID) == places and len(TILE_GRID) == 52
    assert len(set(TILE_GRID.values())) == 52            # no two tiles on one square
    # a few anchors of the NPR layout: the west coast in column 0, Maine top right
    assert (TILE_GRID["WA"], TILE_GRID["OR"], TILE_GRID["CA"]) == ((2, 0), (3, 0), (4, 0))
    assert TILE_GRID["ME"] == (0, 10) and TILE_GRID["TX"] == (7, 3)
    with pytest.raises(ReportError, match=r"no tile for \['XX'\]"):
        tile_map_figure(["CA", "XX"], np.array([0.5, 0.5]))
    with pytest.raises(ReportError, match="2 probabilities for 1 locations"):
        tile_map_figure(["CA"], np.array([0.5, 0.5]))


def test_the_map_colours_follow_p_rising():
    """Rising states orange, falling purple: the tile colours differ where P does."""
    import io

    from PIL import Image

    def png(p: float) -> np.ndarray:
        data = tile_map_figure(sorted(TILE_GRID), np.full(len(TILE_GRID), p))
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.int16)

    up, down = png(0.95), png(0.05)
    assert up.shape == down.shape
    # orange (red > blue) dominates the tiles when everything rises, purple when it falls
    tiles_up = up[(np.abs(up - 255).sum(-1) > 60)]
    tiles_down = down[(np.abs(down - 255).sum(-1) > 60)]
    assert np.mean(tiles_up[:, 0] > tiles_up[:, 2]) > 0.6
    assert np.mean(tiles_down[:, 2] > tiles_down[:, 0]) > 0.6


def test_page_one_is_one_or_two_sentences_with_a_figure():
    fig = FigureItem(fan_chart_figure(
        [dt.date(2025, 9, 6), dt.date(2025, 9, 13)], np.array([10.0, 12.0]),
        [dt.date(2025, 9, 13), dt.date(2025, 9, 20)],
        np.array([[9, 11, 12, 13, 15], [8, 10, 13, 15, 19]], dtype=float),
        nowcast=np.array([True, False]), unit="admissions", wide="95%"), "c", "a")
    table = TableItem(pd.DataFrame({"median": [1]}), "")
    page = PageOne((fig,), "One sentence. Two sentences.", table,
                   (Notice(NoticeKind.LEFT_OUT, "Missouri"),))
    assert page.notices[0].kind is NoticeKind.LEFT_OUT
    with pytest.raises(ReportError, match="one or two sentences, got 3"):
        PageOne((fig,), "One. Two. Three.", table)
    with pytest.raises(ReportError, match="needs the figure"):
        PageOne((), "One.", table)
    with pytest.raises(ReportError, match="do not fit 2 weeks"):
        fan_chart_figure([dt.date(2025, 9, 6)], np.array([1.0]), [dt.date(2025, 9, 13)] * 2,
                         np.zeros((3, 5)), nowcast=np.array([True, False]), unit="u",
                         wide="95%")
    with pytest.raises(ReportError, match="not increasing"):
        fan_chart_figure([dt.date(2025, 9, 6)], np.array([1.0]), [dt.date(2025, 9, 13)],
                         np.array([[5.0, 4, 3, 2, 1]]), nowcast=np.array([False]), unit="u",
                         wide="95%")
    assert word_count("The US: 1,234 (95%: 1,000–1,500) — 3 of 52.") == 8


def _content_with(table: pd.DataFrame) -> ReportContent:
    from pipeline.report.content import Section

    return ReportContent(title="t", reference_date=dt.date(2025, 9, 27), data_vintage="v",
                         sections=(Section("s", "S", (TableItem(table, "wide"),)),),
                         provenance=Provenance(package_version="0"))


@pytest.mark.integration
def test_the_checkers_find_what_they_look_for(tmp_path):
    """A line that cannot wrap runs past the margin and is found; a page that logs an error
    and loads a broken image has both counted."""
    _tools()
    from pipeline.report.render import pdf_bytes

    html = render_html(_content_with(pd.DataFrame({"a": ["x" * 150]})))
    html = html.replace("</style>", "td { white-space: nowrap !important; "
                        "overflow-wrap: normal !important; }</style>")
    (tmp_path / "wide.pdf").write_bytes(pdf_bytes(html)[0])
    assert len(overflowing_text_boxes(tmp_path / "wide.pdf")) >= 1
    page = tmp_path / "bad.html"
    page.write_text("<html><head></head><body><div id='page-1'>"
                    "<img src='data:image/png;base64,AAAA'></div>"
                    "<script>console.error('boom')</script></body></html>")
    found = browser_check(page)
    assert found.page1_images == [0]
    assert len(found.console_errors) >= 2      # the logged error and the broken image


# ----------------------------------------------------------------------------- a real round

@pytest.fixture(scope="module")
def hub_round(tmp_path_factory):
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.hub_round.run import HubRunConfig, run_hub_round

    root = tmp_path_factory.mktemp("hub-page1")
    series = pd.read_parquet(NHSN / "time-series.parquet")
    series[pd.to_datetime(series["as_of"]) >= pd.Timestamp("2025-09-10")].to_parquet(
        root / "time-series.parquet")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
        import_hub_time_series(root / "time-series.parquet")
        run = run_hub_round(HubRunConfig.of_preset("tiny", disease="covid",
                                                   data_source="cache"))
    return root, run


@pytest.mark.slow
def test_horizon_minus_one_is_scored_against_the_last_reported_value(hub_round):
    """The hub's baseline at −1 is a point mass at the round's last reported value: its WIS is
    the absolute error; 0 … 3 are the re-implemented baseline's; the newest round (its week −1
    is the truth's own data) is not scored."""
    from pipeline.members.hub_baseline import HUB_BASELINE
    from pipeline.panels.hub import target_scale
    from pipeline.panels.panel import weeks_ending
    from pipeline.report.hub import (hub_baseline_as_scored, last_reported, like_with_like,
                                     scored_rounds, track_record_table)

    _, run = hub_round
    result = run.results[ADMISSIONS]
    k = result.horizon_index(-1)
    assert scored_rounds(result).tolist() == [True, True, False]
    # the last value each round's own vintage reported, read here from the panel directly
    rnd = result.rounds[0]
    ca = result.places.index("06")
    assert last_reported(result)[ca, 0] == weeks_ending(rnd.panel.histories["06"], rnd.origin,
                                                        1)[0] / target_scale(ADMISSIONS)
    base = hub_baseline_as_scored(result).values
    assert (base[:, :, k] == last_reported(result)[..., None]).all()
    others = [i for i in range(len(result.horizons)) if i != k]
    np.testing.assert_array_equal(base[:, :, others],
                                  result.forecasts[HUB_BASELINE].values[:, :, others])
    scored = like_with_like(result)
    absolute = np.abs(result.truth.values[:, :2, k] - last_reported(result)[:, :2])
    np.testing.assert_allclose(scored.baseline[:, :2, k], absolute, rtol=1e-12, atol=1e-9)
    assert np.isnan(scored.wis[:, 2, k]).all()
    table = track_record_table(result)
    ratio = np.nansum(scored.wis[:, :, k]) / np.nansum(absolute)
    assert table.loc["published", "-1 wk"] == pytest.approx(ratio, rel=1e-12)
    # like with like: the members no longer all read 1.000 at −1 (they share the nowcast there,
    # the baseline is the last reported value)
    assert table.loc["published", "-1 wk"] != pytest.approx(1.0, abs=1e-6)


@pytest.mark.slow
@pytest.mark.integration
def test_hub_page_one_renders_the_map_and_fan_within_150_words(hub_round, tmp_path):
    _tools()
    from pipeline.combine.combiner import PUBLISHED
    from pipeline.report.hub import hub_report_content

    _, run = hub_round
    content = hub_report_content(
        run.results, reference_date=run.reference_date, model_id="flowcast-nfhub",
        data_vintage="as of 2025-09-24", warnings=["a vintage held for review"],
        skipped=run.skipped(), config={},
        notices=[Notice(NoticeKind.LEFT_OUT, "member nf-real left out")])
    assert content.page1 is not None and len(content.page1.figures) == 2
    # the appendix names every location left out, one the data never held included
    assert "wk inc covid prop ed visits: 29 (not in the data)" in \
        content.provenance.extra["locations left out"]
    files = write_report(content, tmp_path)
    pdf = files.pdf_path
    assert pdf_page_images(pdf, 1) == 2
    assert pdf_page_words(pdf, 1) <= MAX_WORDS
    assert overflowing_text_boxes(pdf) == []
    found = browser_check(files.html_path)
    assert (found.page1_images, found.console_errors) == ([1, 1], [])
    text = " ".join(__import__("subprocess").run(
        ["pdftotext", "-f", "1", "-l", "1", str(pdf), "-"], capture_output=True, text=True,
        check=True).stdout.split())
    # the headline's and the table's numbers are the published US quantiles
    published = run.results[ADMISSIONS].quantiles(PUBLISHED)
    newest = published.origins[-1]
    median = {h: published.at(place="US", origin=newest, horizon=h, level=0.5) for h in (-1, 1)}
    assert f"forecast at {median[1]:,.0f}" in text
    assert f"nowcast of {median[-1]:,.0f}" in text
    for notice in ("member nf-real left out", "a vintage held for review", "Missouri"):
        assert notice in text, notice
    assert "CDC COVID-19 Forecast Hub round" in text


def test_page_one_counts_a_long_list_of_left_out_locations_and_the_appendix_names_them():
    """A round missing a few locations of a target names them on page 1; one missing most of
    them (a wide outage) counts them there, within page 1's word budget, and the appendix's
    provenance names every one, those the data never held included."""
    from types import SimpleNamespace

    from pipeline.data.hub.locations import BY_LOCATION
    from pipeline.report.hub import PAGE_ONE_NAMED, missing_locations, round_notices

    every = list(BY_LOCATION)
    kept = ["US", "06", "48", "36"]                  # an outage left four of 53
    results = {"wk inc covid hosp": SimpleNamespace(places=[p for p in every if p != "29"]),
               "wk inc covid prop ed visits": SimpleNamespace(places=kept)}
    skipped = {"wk inc covid prop ed visits": {"12": "'value' is not finite on 2025-09-13"}}
    missing = missing_locations(results, skipped)      # type: ignore[arg-type]
    notices = round_notices(missing, [])
    assert [n.text for n in notices] == [
        "admissions: Missouri (no usable data).",
        f"ED-visit share: {len(every) - len(kept)} of {len(every)} locations, named in the "
        "appendix (no usable data)."]
    assert word_count(" ".join(n.text for n in notices)) < 25
    assert missing["wk inc covid hosp"] == ["29"]
    assert len(missing["wk inc covid prop ed visits"]) == len(every) - len(kept) > PAGE_ONE_NAMED
    assert set(missing["wk inc covid prop ed visits"]) == set(every) - set(kept)
