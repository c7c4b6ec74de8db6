"""Reports: figures from synthetic arrays, self-contained HTML, PDF pages (pdftoppm), Chromium,
and the weekly report of a real tiny-preset run (page 1 = the published forecast's numbers).

The small report below has every section of the weekly report, built the way the forecast flow
builds it (arrays → figure builders → FigureItem; DataFrames → TableItem), from a synthetic SIR
epidemic, so what is drawn is known: observations = ODE solution + noise.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import re
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp

from pipeline.report import checks, figures
from pipeline.report.content import (PNG_SIGNATURE, FigureItem, Provenance, ReportContent,
                                     ReportError, Section, SectionKey, TableItem, nll_table,
                                     paper_vs_ours, stale_data_warning)
from pipeline.report.render import (render_html, render_pdf, render_reproduction, write_report,
                                    write_reproduction)
from tests.browser import (browser_check, chromium_screenshot, external_references, image_stats,
                           missing_tool_reason, overflowing_text_boxes, pdf_page_count,
                           pdf_page_images, pdf_page_words, pdf_to_pngs)

N_DAYS = 160
START = dt.date(2020, 3, 3)
BETA, GAMMA = 0.11, 0.05


# ----------------------------------------------------------------------------- synthetic data

def _sir(n_days: int = N_DAYS) -> np.ndarray:
    def rhs(_t, x):
        s, i, _r = x
        return [-BETA * s * i, BETA * s * i - GAMMA * i, GAMMA * i]
    return solve_ivp(rhs, (0, n_days - 1), [0.99, 0.005, 0.005], t_eval=np.arange(n_days),
                     rtol=1e-9, atol=1e-12).y.T


@pytest.fixture(scope="module")
def epidemic():
    rng = np.random.default_rng(11)
    truth = _sir()
    observed = truth + 0.002 * rng.standard_normal(truth.shape) * np.array([1, 0.3, 1])
    dates = pd.date_range(START, periods=N_DAYS, freq="D")
    sd = np.array([0.004, 0.0015, 0.004]) * (1 + np.arange(N_DAYS)[:, None] / N_DAYS)
    return {"dates": dates, "truth": truth, "observed": observed, "sd": sd}


def _png_ok(png: bytes) -> None:
    assert png.startswith(PNG_SIGNATURE)
    assert len(png) > 5_000


def _figure_stats(png: bytes, tmp_path: Path, name: str):
    path = tmp_path / f"{name}.png"
    path.write_bytes(png)
    return image_stats(path)


def _bands(centre: np.ndarray, sd: np.ndarray) -> np.ndarray:
    """(5, T, 3) quantiles at figures.LEVELS of a normal with these means and sds."""
    z = np.array([-1.645, -0.674, 0.0, 0.674, 1.645])
    return centre[None] + z[:, None, None] * sd[None]


def _weekly_q(median: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(H, 5) quantiles at figures.LEVELS around ``median`` (log-normal-ish, positive)."""
    z = np.array([-1.645, -0.674, 0.0, 0.674, 1.645])
    return median[:, None] * np.exp(z[None, :] * spread[:, None])


@pytest.fixture(scope="module")
def report_figures(epidemic):
    d, obs, truth, sd = epidemic["dates"], epidemic["observed"], epidemic["truth"], epidemic["sd"]
    frame = pd.DataFrame({"date": d, "S": obs[:, 0], "I": obs[:, 1], "R": obs[:, 2]})
    figs = {"series": figures.sir_series_figure(frame, vintage="synthetic test data")}
    figs["forward"] = figures.estimate_band_figure(
        d[30:], obs[30:], _bands(truth[30:], sd[30:]), direction="forward",
        context=(d[30].date(), d[36].date()))
    figs["backward"] = figures.estimate_band_figure(
        d[:130], obs[:130], _bands(truth[:130], sd[:130]), direction="backward")
    for window in (7, 28):
        for direction in ("forward", "backward"):
            figs[f"rollout-{window}-{direction}"] = figures.rollout_figure(
                d, obs, _bands(truth, sd * (1 + window / 28)), window_days=window,
                direction=direction)
    beta_q = BETA + np.array([-0.012, -0.005, 0, 0.005, 0.012])[None] * np.ones((N_DAYS, 1))
    gamma_q = GAMMA + np.array([-0.006, -0.002, 0, 0.002, 0.006])[None] * np.ones((N_DAYS, 1))
    rt_q = beta_q * obs[:, :1] / gamma_q[:, ::-1]
    figs["parameters"] = figures.parameter_figure(d, beta_q, gamma_q, rt_q,
                                                  beta_prior=(0.02, 0.2),
                                                  gamma_prior=(0.005, 0.1))
    ess = 1000 * (0.4 + 0.5 * np.abs(np.sin(np.arange(N_DAYS) / 9)))
    ess[40:43] = 12.0                     # a collapse the figure marks
    figs["smc"] = figures.smc_band_figure(d, obs, _bands(truth, 1.5 * sd), ess=ess,
                                          n_particles=1000)
    steps = np.arange(0, 2001, 50)
    history = pd.concat([
        pd.DataFrame({"step": steps, "variant": v, "train": 1.5 * np.exp(-steps / s) - 2.4,
                      "validation": np.where(steps % 200 == 0,
                                             1.6 * np.exp(-steps / s) - 2.3, np.nan)})
        for v, s in (("Transformer", 400), ("Transformer + KE", 500))])
    figs["loss"] = figures.loss_curve_figure(history)

    # weekly cases of the synthetic epidemic: N·I at every 7th day (I·N = last 7 days' cases)
    population = 100_000
    week_ends = d[6::7][:12]
    weekly = obs[6::7, 1][:12] * population
    targets = pd.date_range(week_ends[-1] + pd.Timedelta(days=7), periods=4, freq="7D")
    cases_q = _weekly_q(weekly[-1] * 0.9 ** np.arange(1, 5), 0.15 * np.arange(1, 5))
    figs["forecast"] = figures.published_forecast_figure(
        week_ends, weekly, weekly / population, targets, cases_q, cases_q / population,
        population)
    past = {}
    for label, scale in (("weekly reported cases", 1.0), ("I (share of the population)",
                                                          1 / population)):
        rows = []
        for h in (1, 4):
            for k, end in enumerate(d[6::7][h:]):
                y = obs[6 + 7 * (k + h), 1] * population
                q = _weekly_q(np.array([y * 1.05]), np.array([0.1 * h]))[0] * scale
                rows.append({"target_end_date": end, "horizon": h, "observed": y * scale,
                             **{f"q{lv:g}": v for lv, v in zip(figures.LEVELS, q)}})
        past[label] = pd.DataFrame(rows)
    figs["past"] = figures.past_forecasts_figure(past, (1, 4))
    figs["pit"] = figures.pit_figure({
        "weekly reported cases": {"published": [9, 10, 11, 10, 9, 10, 10, 11, 10, 10],
                                  "before recalibration": [20, 8, 6, 5, 5, 5, 6, 8, 12, 25]},
        "I (share of the population)": {"published": [10] * 10,
                                        "before recalibration": [18, 9] + [8] * 8}})
    return figs


def _item(figs, key, caption, width="full"):
    return FigureItem(png=figs[key], caption=caption, alt=f"Figure: {caption}", width=width)


def _content(figs, warnings=()) -> ReportContent:
    nll = nll_table({("fw", "Transformer"): -2.468, ("fw", "Transformer + KE"): -2.398,
                     ("fw", "Mamba-SSM"): -1.795, ("bw", "Transformer"): -2.231,
                     ("bw", "Transformer + KE"): -2.092})
    rollouts = [_item(figs, f"rollout-{w}-{d}", f"{d.capitalize()} rollout, {w}-day window: "
                      "full view (left), zoomed on the peak (right); 50% and 90% bands.")
                for w in (7, 28) for d in ("forward", "backward")]
    skill = pd.DataFrame({"1 wk": [0.71, 1.0], "all": [0.9, 1.0]},
                         index=pd.Index(["published", "hub baseline"], name="forecaster"))
    forecast = pd.DataFrame(
        [["730", "562–949"], ["638", "401–1,018"], ["730 (0.084%)", "562–949 (0.064–0.11%)"]],
        columns=["median", "50% interval"],
        index=pd.MultiIndex.from_tuples([("weekly cases", "2020-08-15"),
                                         ("weekly cases", "2020-08-22"),
                                         ("I·N (share)", "2020-08-15")],
                                        names=["forecast", "week ending"]))
    headline = Section(key="headline", title="The next four weeks", items=(
        TableItem(forecast, "Published forecast.", css="headline"),))
    sections = (
        Section.weekly(SectionKey.FORECAST, [_item(figs, "forecast", "Four-week forecast.")]),
        Section.weekly(SectionKey.BACKTEST, [
            TableItem(skill, "Relative WIS by horizon (weeks).", highlight="col-min"),
            _item(figs, "past", "Past forecasts against observations."),
            _item(figs, "pit", "PIT histograms.")], new_page=False),
        Section.weekly(SectionKey.SIR_SERIES, [_item(figs, "series", "Observed S, I, R.")],
                       intro="S, I, R as fractions of the population (synthetic)."),
        Section.weekly(SectionKey.PARAMETERS, [_item(figs, "parameters", "β, γ and R_t.")],
                       alerts=["β not identified by the data: its 90% interval spans 95% of "
                               "the prior range; more words."]),
        Section.weekly(SectionKey.STATE_ESTIMATES, [
            _item(figs, "forward", "Forward estimates with 50% and 90% bands."),
            _item(figs, "backward", "Backward estimates with 50% and 90% bands.")]),
        Section.weekly(SectionKey.ROLLOUTS, rollouts),
        Section.weekly(SectionKey.SMC, [_item(figs, "smc", "NF-seeded SMC, 50% and 90%.")]),
        Section.weekly(SectionKey.NLL, [TableItem(nll, "Mean NLL <b>aggregated</b> over S, I, R "
                                                       "(paper Table 5 layout); lower is better.",
                                                  highlight="row-min")]),
        Section.weekly(SectionKey.TRAINING, [_item(figs, "loss", "Training/validation loss.")],
                       new_page=False),
    )
    provenance = Provenance(package_version="0.1.0", versions={"torch": "2.13.0", "numpy": "2"},
                            config={"preset": "sir-joint", "encoder": "transformer",
                                    "window": 28, "levels": [0.05, 0.5, 0.95]},
                            data_sha256="ab" * 32, checkpoint_sha256="cd" * 32, seed=7)
    return ReportContent(title="San Francisco weekly SIR forecast", reference_date=dt.date(2020, 8, 8),
                         data_vintage="synthetic SIR, β = 0.11, γ = 0.05", sections=sections,
                         provenance=provenance, warnings=tuple(warnings), headline=headline,
                         summary="A test report with <script>alert(1)</script> in its text.")


# ----------------------------------------------------------------------------- figures

@pytest.mark.parametrize("key", ["series", "forward", "backward", "rollout-7-forward",
                                 "rollout-28-backward", "parameters", "smc", "loss", "forecast",
                                 "past", "pit"])
def test_each_figure_is_a_nontrivial_png(report_figures, tmp_path, key):
    png = report_figures[key]
    _png_ok(png)
    (width, height), ink, colours = _figure_stats(png, tmp_path, key)
    assert width == round(figures.FULL_WIDTH_IN * figures.DPI)   # 8.5 in × 110 dpi = 935 px
    assert 300 < height < 1000
    assert 0.03 < ink < 0.6          # drawn, but not a solid block
    assert colours > 20              # lines, bands, text: not a flat image


def test_compartment_colours_are_drawn(report_figures, tmp_path):
    png = report_figures["series"]
    path = tmp_path / "series.png"
    path.write_bytes(png)
    from PIL import Image
    rgb = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3).astype(int)
    for hex_colour in figures.COMPARTMENT_COLORS.values():
        target = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
        assert np.any(np.abs(rgb - target).sum(axis=1) < 30), hex_colour


def test_figure_input_errors_are_named(epidemic):
    d = epidemic["dates"]
    good = epidemic["truth"]
    bands = _bands(good, np.full_like(good, 0.01))
    with pytest.raises(ReportError, match=r"quantiles must have shape \(5, 160, 3\)"):
        figures.estimate_band_figure(d, None, bands[:3])
    with pytest.raises(ReportError, match="lower bound exceeds"):
        figures.estimate_band_figure(d, None, bands[::-1])
    with pytest.raises(ReportError, match="ordered along the levels"):
        figures.parameter_figure(d, np.ones((160, 5)) * [5, 4, 3, 2, 1], np.ones((160, 5)))
    with pytest.raises(ReportError, match="lacks columns"):
        figures.sir_series_figure(pd.DataFrame({"date": d, "S": good[:, 0]}))
    with pytest.raises(ReportError, match="zoom span"):
        figures.rollout_figure(d, good, bands, window_days=7, direction="forward",
                               zoom=(dt.date(2030, 1, 1), dt.date(2030, 2, 1)))


def test_default_zoom_centres_on_peak_of_infections(epidemic):
    d, obs = epidemic["dates"].to_numpy(), epidemic["truth"]
    start, stop = figures.default_zoom(d, obs[:, 1], days=60)
    peak = pd.Timestamp(d[np.argmax(obs[:, 1])]).date()
    assert (stop - start).days == 59
    assert start < peak < stop


# ----------------------------------------------------------------------------- content

def test_content_rejects_bad_items():
    with pytest.raises(ReportError, match="not a PNG"):
        FigureItem(png=b"GIF89a...", caption="x", alt="x")
    with pytest.raises(ReportError, match="alt text"):
        FigureItem(png=PNG_SIGNATURE + b"rest", caption="x", alt=" ")
    with pytest.raises(ReportError, match="empty"):
        TableItem(pd.DataFrame(), "nothing")
    section = Section(key="a", title="A", items=())
    with pytest.raises(ReportError, match="duplicate section keys"):
        ReportContent(title="t", reference_date=dt.date(2020, 1, 1), data_vintage="v",
                      sections=(section, section), provenance=Provenance("0"))


def test_stale_warning_and_nll_layout():
    assert stale_data_warning(dt.date(2022, 3, 10), dt.date(2022, 3, 14)) is None
    text = stale_data_warning(dt.date(2022, 3, 1), dt.date(2022, 3, 14))
    assert "13 days" in text and "2022-03-01" in text
    table = nll_table({("fw", "Transformer"): -2.5, ("bw", "Mamba-SSM"): -1.4})
    assert table.index.tolist() == ["fw", "bw"]
    assert table.columns.tolist() == ["Transformer", "Transformer + KE", "Mamba-SSM"]
    assert table.loc["fw", "Transformer"] == -2.5 and np.isnan(table.loc["fw", "Mamba-SSM"])
    with pytest.raises(ReportError, match="sideways"):
        nll_table({("sideways", "Transformer"): 1.0})


def test_table_copy_is_isolated_from_caller():
    frame = pd.DataFrame({"a": [1.0]})
    item = TableItem(frame, "t")
    frame.loc[0, "a"] = 99.0
    assert item.frame.loc[0, "a"] == 1.0


# ----------------------------------------------------------------------------- HTML

def test_html_is_self_contained_escaped_and_complete(report_figures):
    content = _content(report_figures, warnings=["Data are stale by 9 days."])
    html = render_html(content)
    assert external_references(html) == []
    assert html.count('src="data:image/png;base64,') == 13  # every figure embedded
    for key in SectionKey:
        assert f'id="{key}"' in html and f'href="#{key}"' in html
    assert 'id="provenance"' in html and "ab" * 32 in html
    # page 1: the headline table comes before any warning, check or section
    assert html.index('id="headline"') < html.index('class="warning"') < html.index(
        'class="checks"') < html.index('id="forecast"')
    # a two-level row index: the first level merged over its rows
    assert '<th scope="row" rowspan="2">weekly cases</th>' in html
    # a section's alert is at its top and listed, first clause only, on page 1
    assert html.count("β not identified by the data") == 2
    # flat lists of the configuration on one line
    assert '&#34;levels&#34;: [0.05, 0.5, 0.95]' in html
    assert re.search(r"<td class=\"best\">0\.710</td>", html)     # best of its column
    # text is escaped, never interpreted
    assert "<script>" not in html and "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    assert "&lt;b&gt;aggregated&lt;/b&gt;" in html
    assert "Data are stale by 9 days." in html and 'role="alert"' in html
    # Table 5: best (lowest) NLL per row in bold, negative numbers with a real minus sign,
    # a missing variant as a dash
    assert re.search(r'<td class="best">−2\.468</td>', html)
    assert re.search(r'<td class="best">−2\.231</td>', html)
    assert '<td class="missing">—</td>' in html
    # deterministic: equal content renders to equal bytes
    assert render_html(content) == html


def test_external_reference_detector_catches_each_kind():
    assert external_references('<a href="#x">x</a><img src="data:image/png;base64,AA">') == []
    page = ('<img src="http://e.org/a.png"><a href="https://e.org">l</a>'
            '<link rel="stylesheet" href="s.css"><style>@import "x.css"; '
            'body{background:url(//e.org/b.png)}</style><div style="background:url(c.png)">')
    found = external_references(page)
    assert any("http://e.org/a.png" in f for f in found)
    assert any("https://e.org" in f for f in found)
    assert "<link>" in found
    assert any(f.startswith("@import") for f in found)
    assert any("//e.org/b.png" in f for f in found)
    assert any("c.png" in f for f in found)


def test_pdf_renderer_refuses_external_resources(tmp_path):
    html = ('<html><body><p>x</p><img src="http://example.org/x.png" alt="x"></body></html>')
    with pytest.raises(ReportError, match="external resource 'http://example.org/x.png'"):
        render_pdf(html, tmp_path / "x.pdf")
    assert not (tmp_path / "x.pdf").exists()
    ok = '<html><body><img src="data:image/png;base64,iVBORw0KGgo=" alt="y"><p>y</p></body></html>'
    assert render_pdf(ok, tmp_path / "ok.pdf") == 1


# ----------------------------------------------------------------------------- PDF + PNG pages

def _section_pages(html: str) -> dict[str, int]:
    """Page (1-based) of each h2 heading via WeasyPrint's bookmark tree."""
    import weasyprint

    from pipeline.report.render import _data_only_fetcher

    document = weasyprint.HTML(string=html, url_fetcher=_data_only_fetcher()).render()
    pages: dict[str, int] = {}

    def walk(subtrees):
        for label, target, children, _state in subtrees:
            pages[label] = target[0] + 1
            walk(children)
    walk(document.make_bookmark_tree())
    return pages


def test_pdf_pages_and_png_conversion(report_figures, tmp_path):
    if reason := missing_tool_reason("pdftoppm") or missing_tool_reason("pdfinfo"):
        pytest.skip(reason)
    content = _content(report_figures)
    files = write_report(content, tmp_path / "out")
    assert files.html_path.read_text(encoding="utf-8") == render_html(content)
    n_pages = pdf_page_count(files.pdf_path)
    assert n_pages == files.n_pages
    # page 1 is the headline; then the sections in order, a new-page one on a new page, a
    # short one (new_page=False) right after the previous; the appendix last
    pages = _section_pages(render_html(content))
    headings = [f"{k + 1}. {s.title}" for k, s in enumerate(content.sections)]
    headings.append("Appendix: provenance")
    assert [h for h in pages if h in headings] == headings
    starts = [pages[h] for h in headings]
    assert starts[0] == 2
    for k, section in enumerate(content.sections[1:], start=1):
        assert starts[k] > starts[k - 1] if section.new_page else starts[k] >= starts[k - 1]
    assert starts[-1] > starts[-2]
    rollouts = [s.key for s in content.sections].index(SectionKey.ROLLOUTS)
    assert starts[rollouts + 1] - starts[rollouts] == 2   # 4 tall rollout figures, two a page
    assert n_pages == starts[-1]

    pngs = pdf_to_pngs(files.pdf_path, tmp_path / "pages", dpi=40)
    assert len(pngs) == n_pages
    for png in pngs:
        (width, height), ink, _ = image_stats(png)
        assert (width, height) == (331, 468)          # A4 at 40 dpi: 8.27 × 11.69 in
        assert ink > 0.01, f"{png.name} is blank"
    # figure pages carry a lot of ink
    (_, _), ink_rollout, colours = image_stats(pngs[starts[rollouts] - 1])
    assert ink_rollout > 0.1 and colours > 30


def test_failed_render_leaves_previous_report_intact(report_figures, tmp_path, monkeypatch):
    out = tmp_path / "reports" / "2020-08-09"
    write_report(_content(report_figures), out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    import pipeline.report.render as render

    def broken(_html):
        raise RuntimeError("WeasyPrint crashed")
    monkeypatch.setattr(render, "pdf_bytes", broken)
    with pytest.raises(RuntimeError, match="crashed"):
        write_report(_content(report_figures, warnings=["new run"]), out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert sorted(before) == ["report.html", "report.pdf"]


# ----------------------------------------------------------------------------- Chromium

@pytest.mark.integration
def test_html_renders_in_headless_chromium(report_figures, tmp_path):
    if reason := missing_tool_reason("chromium"):
        pytest.skip(reason)
    html_path = tmp_path / "report.html"
    html_path.write_text(render_html(_content(report_figures, warnings=["stale"])),
                         encoding="utf-8")
    shot = chromium_screenshot(html_path, tmp_path / "shot.png", width=1100, height=1800)
    (width, height), ink, colours = image_stats(shot)
    assert (width, height) == (1100, 1800)
    assert ink > 0.05 and colours > 50     # text, the warning box and the first figure


# ----------------------------------------------------------------------------- reproduction

def test_reproduction_report_tables_beside_paper(report_figures, tmp_path):
    paper = pd.DataFrame({"S": [2.245, 2.110], "I": [2.211, 1.984], "R": [2.304, 2.232]},
                         index=pd.Index(["fw", "bw"], name="direction"))
    ours = pd.DataFrame({"S": [2.301, 2.020], "I": [2.190, 2.004]}, index=paper.index)
    table = paper_vs_ours(paper, ours)
    assert table.columns.tolist() == [("S", "paper"), ("S", "ours"), ("I", "paper"),
                                      ("I", "ours"), ("R", "paper"), ("R", "ours")]
    assert np.isnan(table.loc["fw", ("R", "ours")])
    fig = FigureItem(report_figures["forward"], "Confidence regions.", "regions")
    html = render_reproduction([("Table 3: KL divergence, single trajectory", table)], [fig])
    assert external_references(html) == []
    assert html.count('colspan="2"') == 3                # S, I, R each span paper + ours
    assert ">2.245</td><td>2.301</td>" in html.replace('<td class="">', "<td>")
    files = write_reproduction([("KL", table)], [fig], tmp_path)
    assert files.pdf_path.name == "reproduction.pdf" and files.n_pages == 2
    with pytest.raises(ReportError, match="columns"):
        paper_vs_ours(paper, ours.assign(X=1.0))


# ----------------------------------------------------------------------------- checks

def test_checks_say_trouble_in_words():
    dates = pd.date_range("2022-02-01", periods=28)
    ess = np.full(28, 150.0)
    ess[3] = 2.0
    text = checks.ess_collapse(ess, 200, dates)
    assert text.startswith("Particle filter degenerate")
    assert "below 5% of the particles on 1 of 28 days; minimum 2 of 200 on 2022-02-04" in text
    assert checks.ess_collapse(np.full(28, 150.0), 200, dates) is None
    wide = checks.prior_not_updated("β", np.full(28, 0.03), np.full(28, 0.29), (0.03, 0.3),
                                    dates)
    assert wide.startswith("β not identified by the data: its 90% interval spans 96%")
    assert checks.prior_not_updated("β", np.full(28, 0.1), np.full(28, 0.15), (0.03, 0.3),
                                    dates) is None
    assert checks.prior_not_updated("β", np.zeros(28), np.ones(28), None, dates) is None
    observed = np.array([0.001, 0.026, 0.01])
    over = checks.rollout_overshoot("forward 28-day rollout", [0.002, 0.3, np.nan], observed)
    assert over.startswith("The forward 28-day rollout overshoots: its median I reaches 0.3, "
                           "11.5× the highest I observed (0.026). Chained estimates compound")
    assert checks.rollout_overshoot("x", [0.002, 0.05, np.nan], observed) is None
    # where: a segment started before the observed peak and overshooting after it
    days = pd.date_range("2021-12-20", periods=6)
    rising = np.array([0.01, 0.02, 0.03, 0.02, 0.015, 0.01])
    past = checks.rollout_overshoot("forward 28-day rollout",
                                    [0.01, 0.02, 0.04, 0.05, 0.06, 0.07], rising,
                                    dates=days, anchors=(0, 3), direction="forward")
    assert ("reaches 0.07 on 2021-12-25, 2.3× the highest I observed (0.03 on 2021-12-22). "
            "Its segment starts on 2021-12-23, after the peak: chained estimates") in past
    inside = checks.rollout_overshoot("forward 28-day rollout",
                                      [0.01, 0.02, 0.04, 0.07, 0.06, 0.05], rising,
                                      dates=days, anchors=(0, 4), direction="forward")
    assert "Its segment starts on 2021-12-20, so the peak lies inside it" in inside
    assert "follows the rise it started from past a turn" in inside
    # page 1 shows each check up to its first "; ": the whole finding, no broken parenthesis
    assert inside.split("; ")[0].endswith("could not see")


def test_one_stale_banner_naming_each_datasets_own_source(datasf_dir):
    """DataSF down: one banner; each dataset's line cites its own resource (the deaths and tests
    notes used to carry the cases URL), without the transport's error text."""
    import requests
    import responses

    from pipeline.data.sf.datasf import DATASETS, ClientConfig
    from pipeline.data.sf.series import SFDataConfig, load_sf_series
    from pipeline.forecast.sources import import_exports, staleness_notes

    import_exports([str(datasf_dir)])
    with responses.RequestsMock(assert_all_requests_are_fired=False) as rsps:
        rsps.add(responses.GET, re.compile(r"https://data\.sfgov\.org/.*"),
                 body=requests.ConnectionError("no route to host (test)"))
        series = load_sf_series(SFDataConfig(client=ClientConfig(
            base_url="https://data.sfgov.org", max_retries=1, backoff_base_s=0.0)))
    banner = checks.data_banner(stale=True, vintage=series.vintage.describe(),
                                notes=staleness_notes(series),
                                last_day=dt.date(2022, 3, 2), today=dt.date(2022, 3, 30),
                                source="live")
    assert banner.startswith("Stale data: DataSF could not be reached") and banner.count(
        "Stale data") == 1
    assert "28 days before the run date" in banner
    for key, spec in DATASETS.items():
        source = re.search(rf"{key} \(([^)]*)\)", banner).group(1)
        assert source == spec.resource_url("https://data.sfgov.org"), (key, source)
    assert "Caused by" not in banner and "no route to host" not in banner
    fresh = checks.data_banner(stale=False, vintage="v", notes=(), last_day=dt.date(2022, 3, 2),
                               today=dt.date(2022, 3, 5), source="live")
    assert fresh is None


# ----------------------------------------------------------------------------- a real run

@pytest.fixture(scope="module")
def real_results(datasf_dir, tmp_path_factory):
    """A tiny-preset run on the recorded DataSF exports: ``run_forecast``, without Prefect."""
    from pipeline import forecast as fc

    root = tmp_path_factory.mktemp("real-run")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
        return fc.run_forecast(fc.resolve_config("tiny", data=fc.DataSourceConfig(
            kind="import", import_paths=(str(datasf_dir),))))


@pytest.fixture(scope="module")
def real_content(real_results):
    """The run's report content, every section drawn here (in this process)."""
    from pipeline.forecast.report.weekly import forecast_report_content

    return forecast_report_content(real_results)


@pytest.fixture(scope="module")
def real_report(real_content, tmp_path_factory):
    from pipeline.report.render import pdf_bytes, start_report

    out = tmp_path_factory.mktemp("real-report")
    written = start_report(real_content).write(out)  # as publish does
    assert sorted(p.name for p in out.iterdir()) == ["report.html", "report.pdf"]
    # the PDF laid out in a forked child is the one laid out here, byte for byte
    assert written.pdf_path.read_bytes() == pdf_bytes(written.html_path.read_text())[0]
    return out


def _pdf_text(pdf: Path, page: int) -> str:
    """One page's text, whitespace collapsed (pdftotext -layout keeps table rows together)."""
    text = subprocess.run(["pdftotext", "-layout", "-f", str(page), "-l", str(page), str(pdf),
                           "-"], capture_output=True, text=True, check=True, timeout=60).stdout
    return " ".join(text.split())


@pytest.mark.slow
def test_page_one_carries_the_published_forecast(real_results, real_report):
    """Page 1 of the PDF holds the headline numbers, and they are the published forecast's (the
    hub submission's) medians and quantiles, P(growing) from its paths, R_t per sample."""
    if reason := missing_tool_reason("pdftotext"):
        pytest.skip(reason)
    from pipeline.backtest.writers import hub_frame
    from pipeline.forecast.report.headline import (compute_headline, fmt_count, fmt_prob, fmt_range,
                                          fmt_rt, fmt_share, week_label)

    weekly = real_results.weekly
    latest, n = weekly.latest, weekly.history.population
    at = {lv: int(np.flatnonzero(np.isclose(latest.levels, lv))[0])
          for lv in (0.05, 0.25, 0.5, 0.75, 0.95)}
    # the headline's numbers are the published quantiles, exactly (no re-estimation) ...
    headline = compute_headline(real_results)
    for k, f in enumerate(headline.horizons):
        for target, got in (("cases", f.cases), ("I", f.infectious)):
            v = latest.values[target][k]
            assert (got.median, got.lo50, got.hi50, got.lo90, got.hi90) == (
                v[at[0.5]], v[at[0.25]], v[at[0.75]], v[at[0.05]], v[at[0.95]])
    # ... which are the hub-format file's quantiles
    hub = hub_frame(latest, real_results.weekly.history.population)
    medians = hub[(hub["output_type"] == "quantile") & (hub["output_type_id"] == "0.5")
                  & (hub["target"] == "cases")].sort_values("horizon")["value"].to_numpy()
    np.testing.assert_array_equal(medians, latest.values["cases"][:, at[0.5]])

    pdf = real_report / "report.pdf"
    page1 = _pdf_text(pdf, 1)
    assert page1.startswith(f"FLOWCAST WEEKLY REPORT San Francisco COVID-19 forecast from "
                            f"{weekly.origin.date()}")
    # page 1 (issue 41): the fan chart, two sentences, the weekly cases' table, what was held
    assert pdf_page_images(pdf, 1) == 1 and pdf_page_words(pdf, 1) <= 150
    first, last = headline.horizons[0], headline.horizons[-1]
    assert (f"Weekly reported cases in San Francisco are forecast at "
            f"{fmt_count(first.cases.median)} (90%: {fmt_range(first.cases.lo90, first.cases.hi90)}"
            f") in the week ending {first.target_end}") in page1
    assert f"Probability that cases grow next week: {fmt_prob(headline.p_growing)}" in page1
    for k, h in enumerate(latest.horizons):
        c = latest.values["cases"][k]
        assert (f"(+{h} wk") in page1 and (f"{fmt_count(c[at[0.5]])} "
                f"{fmt_range(c[at[0.25]], c[at[0.75]])} "
                f"{fmt_range(c[at[0.05]], c[at[0.95]])}") in page1, h
    assert page1.count("Old data") == 1          # one notice (imported, years-old exports)
    # page 2: the details page 1 used to hold — the lead, both targets, the facts, the skill
    page1 = _pdf_text(pdf, 2)
    for k, h in enumerate(latest.horizons):
        c, i = latest.values["cases"][k], latest.values["I"][k]
        week = week_label(headline.horizons[k])
        assert week.startswith(f"{(weekly.origin + pd.Timedelta(days=7 * h)).date()} (+{h} wk")
        assert (f"{week} {fmt_count(c[at[0.5]])} {fmt_range(c[at[0.25]], c[at[0.75]])} "
                f"{fmt_range(c[at[0.05]], c[at[0.95]])}") in page1, week

        def pct(x):
            return fmt_share(x).removesuffix("%")
        assert (f"{week} {fmt_count(n * i[at[0.5]])} ({fmt_share(i[at[0.5]])}) "
                f"{fmt_range(n * i[at[0.25]], n * i[at[0.75]])} "
                f"({pct(i[at[0.25]])}–{pct(i[at[0.75]])}%) "
                f"{fmt_range(n * i[at[0.05]], n * i[at[0.95]])} "
                f"({pct(i[at[0.05]])}–{pct(i[at[0.95]])}%)") in page1, week
    now = weekly.history.I[-1] * n
    assert f"About {fmt_count(now)} people in San Francisco are infectious" in page1
    this_week = weekly.history.up_to(weekly.origin).weekly_cases()[-1]
    p = np.mean(latest.paths[:, 0, 1] * n > this_week)
    assert f"{fmt_prob(p)} that next week's cases exceed this week's ({fmt_count(this_week)}" \
        in page1
    x = real_results.latest.samples["forward"].double().numpy()
    names = list(real_results.latest.names)
    s, beta, gamma = (x[:, names.index(c)] for c in ("S", "beta", "gamma"))
    rt = (beta * s / gamma)[gamma > 0]
    q = np.quantile(rt, [0.5, 0.25, 0.75, 0.05, 0.95])
    assert (f"{fmt_rt(q[0])} (50%: {fmt_rt(q[1])}–{fmt_rt(q[2])}; 90%: {fmt_rt(q[3])}–"
            f"{fmt_rt(q[4])})") in page1
    summary = weekly.summary()["by_target"]
    for target, label in (("cases", "weekly reported cases"), ("I", "infectious share I")):
        pub = summary[target]["published"]
        rel = pub["relative_wis_vs_baseline"]
        cells = [rel[f"h{h}"] for h in latest.horizons] + [rel["all"], pub["coverage50"],
                                                           pub["coverage90"]]
        assert f"{label} " + " ".join(f"{v:.2f}" for v in cells) in page1, label
    assert page1.count("Old data") == 1          # one banner (imported, years-old exports)
    assert "1. Forecast" not in page1            # pages 1-2 are the headline only ...
    assert "1. Forecast: the last 12 weeks" in _pdf_text(pdf, 3)


@pytest.mark.slow
def test_real_report_pages_are_neither_blank_nor_mixed_conventions(real_results, real_report,
                                                                   tmp_path):
    if reason := missing_tool_reason("pdftoppm"):
        pytest.skip(reason)
    html = (real_report / "report.html").read_text(encoding="utf-8")
    assert external_references(html) == []
    # one interval convention: 50% and 90%, never σ bands or 95% intervals
    for stray in ("±", "2σ", "3σ", "95%", "97.5%"):
        assert stray not in html, stray
    pdf = real_report / "report.pdf"
    n_pages = pdf_page_count(pdf)
    assert n_pages <= 15
    # tables fit their page (issue 41: the member and backtest tables were cut at the margin)
    assert overflowing_text_boxes(pdf) == []
    if missing_tool_reason("chromium") is None:
        found = browser_check(real_report / "report.html")
        assert (found.page1_images, found.console_errors) == ([1], [])
    for png in pdf_to_pngs(pdf, tmp_path / "pages", dpi=30):
        assert image_stats(png)[1] > 0.02, f"{png.name} is nearly blank"


@pytest.mark.slow
def test_diagnostics_drawn_in_a_child_are_those_drawn_here(real_results, real_content):
    """Diagnostic sections drawn in a forked child (as publish draws half of them): the report
    holds the same sections, captions and images as when all are drawn here."""
    from pipeline.forecast.report.diagnostics import start_diagnostics
    from pipeline.forecast.report.weekly import forecast_report_content

    def parts(content):
        return [(s.key, [getattr(i, "png", None) for i in s.items],
                 [getattr(i, "caption", None) for i in s.items]) for s in content.sections]

    here = real_content
    forked = start_diagnostics(real_results.model_outputs())
    assert forked.build.process is not None          # drawn in a child process
    assert parts(forecast_report_content(real_results, forked)) == parts(here)


@pytest.mark.slow
def test_malformed_diagnostic_is_named_and_a_renamed_field_fails(real_results, monkeypatch):
    import io

    from PIL import Image

    from pipeline.forecast.report.weekly import forecast_report_content
    from pipeline.report import figures

    # which sections are drawn is the question, not their pictures (the other tests draw
    # them): every figure's PNG encoding skipped
    blank = io.BytesIO()
    Image.new("RGB", (1, 1)).save(blank, format="png")
    monkeypatch.setattr(figures, "_png", lambda fig: blank.getvalue())

    smc = real_results.smc
    broken = dataclasses.replace(real_results, smc=dataclasses.replace(
        smc, result=dataclasses.replace(smc.result, state_names=("x", "y", "z"))))
    content = forecast_report_content(broken)
    assert "smc" not in [s.key for s in content.sections]
    assert any(w.startswith("The SMC section could not be drawn: the SMC result lacks "
                            "components ['S', 'I', 'R']") for w in content.warnings)
    renamed = dataclasses.replace(real_results, models=SimpleNamespace(key="k", reused=True))
    with pytest.raises(AttributeError, match="histories"):
        forecast_report_content(renamed)       # a bug surfaces; it is not a warning


@pytest.mark.slow
def test_summary_artifact_and_index_carry_the_headline(real_results):
    import html
    import json

    from pipeline.forecast.report.headline import compute_headline, fmt_count, markdown
    from pipeline.outputs.run_folders import RunRecord, render_index_html

    h = compute_headline(real_results)
    banner = "Stale data: DataSF could not be reached (every retry failed)."
    md = markdown(h, banner, "reports/2022-03-02/report.html")
    assert md.count("Stale data") == 1
    first = h.horizons[0]
    assert f"| {first.target_end} | {fmt_count(first.cases.median)} |" in md
    assert "relative WIS vs the hub baseline" in md and "R_t" in md
    record = RunRecord(reference_date="2022-03-02", run_id="r", finished_at="t",
                       data_stale=False, data_vintage="2022-03-21", model_key="k", seed=0,
                       preset="tiny", files=("report.html",),
                       summary={"headline": json.loads(json.dumps(h.to_dict()))})
    assert html.escape(h.one_line()) in render_index_html([record])


def test_rollout_band_quantiles_are_nanquantiles_of_the_paths():
    """The rollout figure's bands: np.nanquantile's values (NaN before the first window, a day
    NaN on some paths), computed through np.quantile where every path has a value."""
    import warnings

    from pipeline.forecast.report.diagnostics import LEVELS, _path_quantiles

    rng = np.random.default_rng(0)
    samples = rng.lognormal(size=(64, 50, 3))
    samples[:, :10] = np.nan
    samples[:7, 20, 1] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nanquantile(samples, LEVELS, axis=0)
    assert np.array_equal(_path_quantiles(samples), expected, equal_nan=True)
