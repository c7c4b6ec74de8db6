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
