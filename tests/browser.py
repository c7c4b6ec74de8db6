"""Test helpers that look at rendered reports: PDF pages (poppler) and HTML (headless Chromium).

System packages: ``poppler-utils`` (pdfinfo, pdftoppm) and ``chromium`` are installed by
``scripts/install-system-deps.sh`` (the README's set-up). ``missing_tool_reason`` returns why a
tool cannot be used, for ``pytest.skip``; it returns None when the tool is there.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
from PIL import Image

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# From docs/../shared/notes/stack.md; --host-resolver-rules makes any network lookup fail,
# so a page that tried to load something would show it rather than fetch it.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--hide-scrollbars", "--host-resolver-rules=MAP * ~NOTFOUND")


def find_chromium() -> str | None:
    for name in CHROMIUM_CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


def missing_tool_reason(tool: str) -> str | None:
    if tool == "chromium":
        if find_chromium() is None:
            return ("headless Chromium not found (tried " + ", ".join(CHROMIUM_CANDIDATES)
                    + "); install with scripts/install-system-deps.sh (Debian package chromium)")
        return None
    if shutil.which(tool) is None:
        return f"{tool} not found; install poppler-utils with scripts/install-system-deps.sh"
    return None


def pdf_page_count(pdf: Path) -> int:
    out = subprocess.run(["pdfinfo", str(pdf)], capture_output=True, text=True, check=True,
                         timeout=60).stdout
    match = re.search(r"^Pages:\s+(\d+)", out, flags=re.MULTILINE)
    if not match:
        raise AssertionError(f"pdfinfo printed no page count for {pdf}:\n{out}")
    return int(match.group(1))


def pdf_to_pngs(pdf: Path, out_dir: Path, dpi: int = 50) -> list[Path]:
    """One PNG per page (``page-1.png`` ...), sorted by page number."""
    out_dir.mkdir(parents=True, exist_ok=True)
    subprocess.run(["pdftoppm", "-png", "-r", str(dpi), str(pdf), str(out_dir / "page")],
                   check=True, timeout=120, capture_output=True)
    pages = list(out_dir.glob("page-*.png"))
    return sorted(pages, key=lambda p: int(p.stem.rsplit("-", 1)[1]))


def chromium_screenshot(html: Path, png: Path, width: int = 1100, height: int = 2400,
                        timeout_s: float = 90.0) -> Path:
    """Screenshot ``html`` (a file) in headless Chromium with a fresh profile directory."""
    binary = find_chromium()
    if binary is None:
        raise FileNotFoundError(missing_tool_reason("chromium"))
    with tempfile.TemporaryDirectory(prefix="flowcast-chromium-") as profile:
        cmd = [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
               f"--screenshot={png}", f"--window-size={width},{height}",
               html.resolve().as_uri()]
        env = {**os.environ, "HOME": profile}
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env)
    if not png.exists():
        raise AssertionError(f"chromium wrote no screenshot (rc={result.returncode}):\n"
                             f"{result.stderr[-2000:]}")
    return png


def image_stats(png: Path) -> tuple[tuple[int, int], float, int]:
    """(width, height), the fraction of non-white pixels, and the number of distinct colours."""
    with Image.open(png) as img:
        rgb = np.asarray(img.convert("RGB"), dtype=np.int16)
    non_white = np.any(rgb < 245, axis=-1).mean()
    colours = len(np.unique(rgb.reshape(-1, 3)[::7], axis=0))
    return (rgb.shape[1], rgb.shape[0]), float(non_white), colours


class _ReferenceCollector(HTMLParser):
    """Every URL-bearing attribute value of every tag."""

    URL_ATTRS = {"src", "href", "srcset", "action", "poster", "data", "background", "formaction",
                 "xlink:href", "manifest", "ping", "cite", "longdesc", "usemap", "icon"}

    def __init__(self) -> None:
        super().__init__()
        self.references: list[tuple[str, str, str]] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        for name, value in attrs:
            if name in self.URL_ATTRS and value is not None:
                self.references.append((tag, name, value))
            if name == "style" and value and "url(" in value:
                self.references.append((tag, "style", value))


def external_references(html: str) -> list[str]:
    """Everything in the page that could make a request: returns the offending references.

    Allowed: ``data:`` URIs and in-page anchors (``#id``). Anything else (http(s), //host,
    relative paths, file:) is reported, as are CSS url()/@import other than data:, and
    <link>, <script>, <iframe>, <object>, <embed> elements.
    """
    collector = _ReferenceCollector()
    collector.feed(html)
    bad = [f"<{tag} {attr}={value[:80]!r}>" for tag, attr, value in collector.references
           if not (value.startswith("data:") or value.startswith("#"))]
    bad += [f"<{tag}>" for tag in collector.tags
            if tag in {"link", "script", "iframe", "object", "embed", "base"}]
    for match in re.finditer(r"url\(\s*['\"]?([^'\")]*)", html):
        if not match.group(1).startswith("data:"):
            bad.append(f"url({match.group(1)[:80]})")
    bad += [f"@import {m.group(0)[:80]}" for m in re.finditer(r"@import[^;]*;", html)]
    return bad


# ----------------------------------------------------------------------------- PDF text layout

_WORD_BOX = re.compile(r'<word xMin="([\d.]+)" yMin="([\d.]+)" xMax="([\d.]+)" yMax="([\d.]+)">'
                       r'([^<]*)</word>')
_PAGE_BOX = re.compile(r'<page width="([\d.]+)" height="([\d.]+)">')
PT_PER_MM = 72 / 25.4


def pdf_word_boxes(pdf: Path) -> list[list[tuple[float, float, float, float, str]]]:
    """Per page, every word's box (xMin, yMin, xMax, yMax in points) and text
    (``pdftotext -bbox``)."""
    out = subprocess.run(["pdftotext", "-bbox", str(pdf), "-"], capture_output=True, text=True,
                         check=True, timeout=120).stdout
    pages = []
    for chunk in out.split("<page ")[1:]:
        pages.append([(float(a), float(b), float(c), float(d), w)
                      for a, b, c, d, w in _WORD_BOX.findall(chunk)])
    return pages


def pdf_page_width(pdf: Path) -> float:
    out = subprocess.run(["pdftotext", "-bbox", "-f", "1", "-l", "1", str(pdf), "-"],
                         capture_output=True, text=True, check=True, timeout=60).stdout
    match = _PAGE_BOX.search(out)
    if not match:
        raise AssertionError(f"pdftotext -bbox printed no page size for {pdf}")
    return float(match.group(1))


def overflowing_text_boxes(pdf: Path, right_margin_mm: float = 14.0, slack_pt: float = 1.0
                           ) -> list[tuple[int, str, float]]:
    """(page, word, xMax) of every word whose box runs past the page's right margin (the
    stylesheet's 14 mm), i.e. text cut or squeezed off the printed area."""
    limit = pdf_page_width(pdf) - right_margin_mm * PT_PER_MM + slack_pt
    return [(page, word, x1) for page, words in enumerate(pdf_word_boxes(pdf), start=1)
            for _, _, x1, _, word in words if x1 > limit]


def pdf_page_words(pdf: Path, page: int = 1) -> int:
    """Words of text on one page (a token holding a letter or digit; figures are images)."""
    text = subprocess.run(["pdftotext", "-f", str(page), "-l", str(page), str(pdf), "-"],
                          capture_output=True, text=True, check=True, timeout=60).stdout
    return sum(1 for token in text.split() if any(ch.isalnum() for ch in token))


def pdf_page_images(pdf: Path, page: int = 1) -> int:
    """Images drawn on one page (``pdfimages -list``), soft masks not counted."""
    out = subprocess.run(["pdfimages", "-list", "-f", str(page), "-l", str(page), str(pdf)],
                         capture_output=True, text=True, check=True, timeout=60).stdout
    rows = [line.split() for line in out.splitlines()[2:] if line.strip()]
    return sum(1 for row in rows if len(row) > 2 and row[2] == "image")


# ----------------------------------------------------------------------------- browser check

_PROBE = """<script>
(function () {
  var errors = [];
  window.addEventListener("error", function (e) {
    var t = e.target;
    errors.push(t && t.tagName ? "failed to load <" + t.tagName.toLowerCase() + ">" : String(e.message));
  }, true);
  window.addEventListener("load", function () {
    var shown = [].map.call(document.querySelectorAll("#page-1 img"), function (img) {
      var box = img.getBoundingClientRect();
      return (img.complete && img.naturalWidth > 0 && box.width > 50 && box.height > 50) ? 1 : 0;
    });
    document.body.setAttribute("data-probe-images", shown.join(","));
    document.body.setAttribute("data-probe-errors", errors.join(" | "));
  });
})();
</script>"""


@dataclass(frozen=True)
class BrowserCheck:
    """What headless Chromium saw: per image of page 1, 1 if it decoded and has a size on the
    page; every console error."""

    page1_images: list[int]
    console_errors: list[str]


def browser_check(html: Path, timeout_s: float = 90.0) -> BrowserCheck:
    """Load the report in headless Chromium: which of page 1's images decoded and have a size on
    the page, and the console errors — every console message the page made (it has no script of
    its own, so any is the browser complaining) plus resources that failed to load. A probe
    script (writing attributes, logging nothing) is added to a copy; the report itself has none."""
    binary = find_chromium()
    if binary is None:
        raise FileNotFoundError(missing_tool_reason("chromium"))
    with tempfile.TemporaryDirectory(prefix="flowcast-chromium-") as profile:
        probe = Path(profile) / "probe.html"
        text = html.read_text(encoding="utf-8")
        probe.write_text(text.replace("<head>", "<head>" + _PROBE, 1), encoding="utf-8")
        cmd = [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--enable-logging=stderr",
               "--v=0", "--window-size=1100,2400", "--dump-dom", probe.as_uri()]
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                                env={**os.environ, "HOME": profile})
    images = re.search(r'data-probe-images="([^"]*)"', result.stdout)
    failed = re.search(r'data-probe-errors="([^"]*)"', result.stdout)
    if images is None or failed is None:
        raise AssertionError(f"chromium did not run the probe (rc={result.returncode}):\n"
                             f"{result.stderr[-2000:]}")
    console = [line for line in result.stderr.splitlines() if ":CONSOLE" in line]
    errors = console + [e for e in failed.group(1).split(" | ") if e]
    return BrowserCheck([int(x) for x in images.group(1).split(",") if x], errors)
