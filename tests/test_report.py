"""Reports: figures from synthetic arrays, self-contained HTML, PDF pages (pdftoppm), Chromium.

The small report below has every section of the weekly report, built the way the forecast flow
builds it (arrays → figure builders → FigureItem; DataFrames → TableItem), from a synthetic SIR
epidemic, so what is drawn is known: observations = ODE solution + noise.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp

from pipeline.backtest import (BacktestConfig, PersistenceForecaster, run_backtest,
                               summary_by_horizon)
from pipeline.report import figures
from pipeline.report.content import (PNG_SIGNATURE, FigureItem, Provenance, ReportContent,
                                     ReportError, Section, SectionKey, TableItem, nll_table,
                                     paper_vs_ours, stale_data_warning)
from pipeline.report.render import (render_html, render_pdf, render_reproduction, write_report,
                                    write_reproduction)
from tests.browser import (chromium_screenshot, external_references, image_stats,
                           missing_tool_reason, pdf_page_count, pdf_to_pngs)

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


@pytest.fixture(scope="module")
def report_figures(epidemic):
    d, obs, truth, sd = epidemic["dates"], epidemic["observed"], epidemic["truth"], epidemic["sd"]
    frame = pd.DataFrame({"date": d, "S": obs[:, 0], "I": obs[:, 1], "R": obs[:, 2]})
    figs = {"series": figures.sir_series_figure(frame, vintage="synthetic test data")}
    figs["forward"] = figures.estimate_band_figure(
        d[30:], obs[30:], truth[30:], truth[30:] - 2 * sd[30:], truth[30:] + 2 * sd[30:],
        direction="forward", context=(d[30].date(), d[36].date()))
    figs["backward"] = figures.estimate_band_figure(
        d[:130], obs[:130], truth[:130], truth[:130] - 2 * sd[:130], truth[:130] + 2 * sd[:130],
        direction="backward")
    for window in (7, 28):
        for direction in ("forward", "backward"):
            width = 2 * sd * (1 + window / 28)
            figs[f"rollout-{window}-{direction}"] = figures.rollout_figure(
                d, obs, truth, truth - width, truth + width, window_days=window,
                direction=direction)
    beta_q = np.column_stack([np.full(N_DAYS, BETA - 0.01), np.full(N_DAYS, BETA),
                              np.full(N_DAYS, BETA + 0.012)])
    gamma_q = np.column_stack([np.full(N_DAYS, GAMMA - 0.006), np.full(N_DAYS, GAMMA),
                               np.full(N_DAYS, GAMMA + 0.005)])
    figs["parameters"] = figures.parameter_figure(d, beta_q, gamma_q, beta_prior=(0.02, 0.2),
                                                  gamma_prior=(0.005, 0.1))
    ess = 1000 * (0.4 + 0.5 * np.abs(np.sin(np.arange(N_DAYS) / 9)))
    figs["smc"] = figures.smc_band_figure(d, obs, truth, truth - 3 * sd, truth + 3 * sd,
                                          ess=ess, n_particles=1000)
    steps = np.arange(0, 2001, 50)
    history = pd.concat([
        pd.DataFrame({"step": steps, "variant": v, "train": 1.5 * np.exp(-steps / s) - 2.4,
                      "validation": np.where(steps % 200 == 0,
                                             1.6 * np.exp(-steps / s) - 2.3, np.nan)})
        for v, s in (("Transformer", 400), ("Transformer + KE", 500))])
    figs["loss"] = figures.loss_curve_figure(history)

    series = pd.DataFrame({"date": d, "S": obs[:, 0], "I": obs[:, 1], "R": obs[:, 2]})
    result = run_backtest(series, [PersistenceForecaster(),
                                   PersistenceForecaster(name="persistence (no symmetry)",
                                                         symmetrize=False)],
                          BacktestConfig(n_samples=100))
    by_h = summary_by_horizon(result)
    figs["backtest"] = figures.backtest_figure(by_h)
    future = np.random.default_rng(1).normal(obs[-1], 0.004, size=(200, 28, 3))
    figs["forecast"] = figures.forecast_fan_figure(
        d, obs, pd.date_range(d[-1] + pd.Timedelta(days=1), periods=28), future)
    return figs, by_h


def _item(figs, key, caption, width="full"):
    return FigureItem(png=figs[key], caption=caption, alt=f"Figure: {caption}", width=width)


def _content(report_figures, warnings=()) -> ReportContent:
    figs, by_h = report_figures
    nll = nll_table({("fw", "Transformer"): -2.468, ("fw", "Transformer + KE"): -2.398,
                     ("fw", "Mamba-SSM"): -1.795, ("bw", "Transformer"): -2.231,
                     ("bw", "Transformer + KE"): -2.092})
    rollouts = [_item(figs, f"rollout-{w}-{d}", f"{d.capitalize()} rollout, {w}-day window: "
                      "full view (left), zoomed on the peak (right); mean ± 2σ.")
                for w in (7, 28) for d in ("forward", "backward")]
    backtest_table = by_h.pivot(index="horizon", columns="forecaster", values="relative_wis")
    sections = (
        Section.weekly(SectionKey.SIR_SERIES, [_item(figs, "series", "Observed S, I, R.")],
                       intro="S, I, R as fractions of the population (synthetic)."),
        Section.weekly(SectionKey.FORECAST, [_item(figs, "forecast", "Four-week forecast.")]),
        Section.weekly(SectionKey.STATE_ESTIMATES, [
            _item(figs, "forward", "Forward estimates with 2σ bands."),
            _item(figs, "backward", "Backward estimates with 2σ bands.")]),
        Section.weekly(SectionKey.ROLLOUTS, rollouts),
        Section.weekly(SectionKey.PARAMETERS, [_item(figs, "parameters", "β and γ, 95% CrI.")]),
        Section.weekly(SectionKey.SMC, [_item(figs, "smc", "NF-seeded SMC, mean ± 3σ.")]),
        Section.weekly(SectionKey.NLL, [TableItem(nll, "Mean NLL <b>aggregated</b> over S, I, R "
                                                       "(paper Table 5 layout); lower is better.",
                                                  highlight="row-min")]),
        Section.weekly(SectionKey.TRAINING, [_item(figs, "loss", "Training/validation loss.")]),
        Section.weekly(SectionKey.BACKTEST, [
            _item(figs, "backtest", "Relative WIS and coverage by horizon."),
            TableItem(backtest_table, "Relative WIS by horizon (weeks).")]),
    )
    provenance = Provenance(package_version="0.1.0", versions={"torch": "2.13.0", "numpy": "2"},
                            config={"preset": "sir-joint", "encoder": "transformer",
                                    "window": 28},
                            data_sha256="ab" * 32, checkpoint_sha256="cd" * 32, seed=7)
    return ReportContent(title="San Francisco weekly SIR forecast", reference_date=dt.date(2020, 8, 9),
                         data_vintage="synthetic SIR, β = 0.11, γ = 0.05", sections=sections,
                         provenance=provenance, warnings=tuple(warnings),
                         summary="A test report with <script>alert(1)</script> in its text.")


# ----------------------------------------------------------------------------- figures

@pytest.mark.parametrize("key", ["series", "forward", "backward", "rollout-7-forward",
                                 "rollout-28-backward", "parameters", "smc", "loss", "backtest",
                                 "forecast"])
def test_each_figure_is_a_nontrivial_png(report_figures, tmp_path, key):
    png = report_figures[0][key]
    _png_ok(png)
    (width, height), ink, colours = _figure_stats(png, tmp_path, key)
    assert width == round(figures.FULL_WIDTH_IN * figures.DPI)   # 8.5 in × 110 dpi = 935 px
    assert 300 < height < 1000
    assert 0.03 < ink < 0.6          # drawn, but not a solid block
    assert colours > 20              # lines, bands, text: not a flat image


def test_compartment_colours_are_drawn(report_figures, tmp_path):
    png = report_figures[0]["series"]
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
    with pytest.raises(ReportError, match=r"mean must have shape \(160, 3\)"):
        figures.estimate_band_figure(d, None, good[:, :2], good, good)
    with pytest.raises(ReportError, match="lower bound exceeds"):
        figures.estimate_band_figure(d, None, good, good + 1, good)
    with pytest.raises(ReportError, match="lower ≤ median ≤ upper"):
        figures.parameter_figure(d, np.ones((160, 3)) * [3, 2, 1], np.ones((160, 3)))
    with pytest.raises(ReportError, match="lacks columns"):
        figures.sir_series_figure(pd.DataFrame({"date": d, "S": good[:, 0]}))
    with pytest.raises(ReportError, match="zoom span"):
        figures.rollout_figure(d, good, good, good, good, window_days=7, direction="forward",
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
    assert html.count('src="data:image/png;base64,') == 12  # every figure embedded
    for key in SectionKey:
        assert f'id="{key}"' in html and f'href="#{key}"' in html
    assert 'id="provenance"' in html and "ab" * 32 in html
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
    # every section starts on a new page, in order, provenance last
    pages = _section_pages(render_html(content))
    headings = [f"{k + 1}. {s.title}" for k, s in enumerate(content.sections)] + ["Provenance"]
    assert [h for h in pages if h in headings] == headings
    starts = [pages[h] for h in headings]
    assert starts[0] == 1 and all(b > a for a, b in zip(starts, starts[1:]))
    # 4 tall rollout figures take 2 pages (two per page), every other section one
    assert starts[4] - starts[3] == 2
    assert n_pages == starts[-1] == len(headings) + 1

    pngs = pdf_to_pngs(files.pdf_path, tmp_path / "pages", dpi=40)
    assert len(pngs) == n_pages
    for png in pngs:
        (width, height), ink, _ = image_stats(png)
        assert (width, height) == (331, 468)          # A4 at 40 dpi: 8.27 × 11.69 in
        assert ink > 0.01, f"{png.name} is blank"
    # figure pages carry a lot of ink
    (_, _), ink_rollout, colours = image_stats(pngs[starts[3] - 1])
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
    fig = FigureItem(report_figures[0]["forward"], "Confidence regions.", "regions")
    html = render_reproduction([("Table 3: KL divergence, single trajectory", table)], [fig])
    assert external_references(html) == []
    assert html.count('colspan="2"') == 3                # S, I, R each span paper + ours
    assert ">2.245</td><td>2.301</td>" in html.replace('<td class="">', "<td>")
    files = write_reproduction([("KL", table)], [fig], tmp_path)
    assert files.pdf_path.name == "reproduction.pdf" and files.n_pages == 2
    with pytest.raises(ReportError, match="columns"):
        paper_vs_ours(paper, ours.assign(X=1.0))


# ----------------------------------------------------------------------------- weekly adapter

@dataclasses.dataclass(frozen=True)
class _FakeConfig:
    window: int = 5
    smc_particles: int = 200
    seed: int = 3


class _Roll:
    """Duck type of pipeline.rollout.RolloutResult (times in days since the first date)."""

    def __init__(self, times, mean, std):
        self.times, self.mean, self.std = times, mean, std
        self.names = ("S", "I", "R", "beta", "gamma")

    def band(self, n_sigma):
        return self.mean - n_sigma * self.std, self.mean + n_sigma * self.std


def _fake_results(epidemic, *, stale: bool, break_smc: bool = False):
    from types import SimpleNamespace

    import torch

    d, obs, truth = epidemic["dates"][:70], epidemic["observed"][:70], epidemic["truth"][:70]
    sir = pd.DataFrame({"date": d, "S": obs[:, 0], "I": obs[:, 1], "R": obs[:, 2]})
    joint = np.column_stack([truth, np.full(70, BETA), np.full(70, GAMMA)])
    sd = np.column_stack([np.full((70, 3), 0.004), np.full(70, 0.005), np.full(70, 0.003)])
    names = ("S", "I", "R", "beta", "gamma")
    parameters = pd.concat([pd.DataFrame({
        "direction": direction, "date": d.strftime("%Y-%m-%d"), "component": name,
        "mean": joint[:, k], "std": sd[:, k], "q0.025": joint[:, k] - 2 * sd[:, k],
        "q0.5": joint[:, k], "q0.975": joint[:, k] + 2 * sd[:, k]})
        for direction in ("forward", "backward") for k, name in enumerate(names)])
    rollouts = {(direction, every): _Roll(np.arange(70.0), torch.as_tensor(joint),
                                          torch.as_tensor(sd))
                for direction in ("forward", "backward") for every in (7, 28)}
    rng = np.random.default_rng(0)
    future_dates = pd.date_range(d[-1] + pd.Timedelta(days=1), periods=28, freq="D")
    future = torch.as_tensor(truth[-1] + 0.003 * rng.standard_normal((200, 28, 3)))
    smc_dates = d[-28:]
    smc_result = SimpleNamespace(
        state_names=names, mean=torch.as_tensor(joint[-28:])[None],
        sigma_band=lambda n: (torch.as_tensor(joint[-28:] - n * sd[-28:])[None],
                              torch.as_tensor(joint[-28:] + n * sd[-28:])[None]),
        ess=torch.full((1, 28), 150.0), num_particles=200)
    if break_smc:
        smc_result.state_names = ("x", "y")
    history = [{"iteration": i, "train_loss": 3.0 / i, "val_nll": 3.2 / i} for i in range(1, 21)]
    models = SimpleNamespace(key="k" * 64, reused=True, encoder="transformer", path=Path("/nope"),
                             histories={"forward": history, "backward": history})
    config = _FakeConfig()
    return SimpleNamespace(
        config=config, sir_frame=sir, vintage="DataSF export, data as of 2020-05-11",
        stale=stale, stale_notes=("cases: fetch failed; using the cache",) if stale else (),
        models=models, rollouts=rollouts, parameters=parameters,
        future=SimpleNamespace(dates=future_dates, samples=future, reference_date=d[-1].date()),
        nll=pd.DataFrame({"direction": ["forward", "backward"], "variant": ["transformer"] * 2,
                          "locations": [20, 20], "mean_nll": [-2.4, -2.2]}),
        smc=SimpleNamespace(result=smc_result, dates=smc_dates))


@pytest.mark.slow
def test_weekly_report_content_from_forecast_results(epidemic):
    from pipeline.report.weekly import forecast_report_content

    content = forecast_report_content(_fake_results(epidemic, stale=True))
    keys = [s.key for s in content.sections]
    assert keys == ["sir-series", "forecast", "state-estimates", "rollouts", "parameters", "smc",
                    "nll", "training"]                  # no backtest in these results
    assert any("fetch failed" in w for w in content.warnings)
    assert any(w.startswith("Data are stale") for w in content.warnings)
    assert content.provenance.seed == 3 and len(content.provenance.data_sha256) == 64
    nll = content.sections[6].items[0].frame
    assert nll.loc["fw", "transformer"] == -2.4 and nll.loc["bw", "transformer"] == -2.2
    beta_row = content.sections[4].items[1].frame.loc["β (per day)"]
    assert beta_row["median"] == pytest.approx(BETA)
    assert len(content.sections[3].items) == 4         # 7/28 days × forward/backward


@pytest.mark.slow
def test_weekly_report_files_name_a_section_it_could_not_draw(epidemic, tmp_path):
    from pipeline.report import build_forecast_report

    names = build_forecast_report(_fake_results(epidemic, stale=False, break_smc=True), tmp_path)
    assert names == ["report.html", "report.pdf"]
    html = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert external_references(html) == []
    assert 'id="smc"' not in html and 'id="rollouts"' in html
    assert "The SMC section could not be drawn: ValueError" in html
    assert pdf_page_count(tmp_path / "report.pdf") >= 8
