"""Where a weekly run writes: ``<root>/<reference-date>/``, staged then promoted, plus an index.
(A California county's runs have their own root, ``<output_dir>/<county-slug>/``:
``pipeline.forecast.publish.output_root``.)

A run writes everything into a hidden staging directory beside the final one
(``<root>/.staging-<date>-<run-id>/``). Only when the whole run succeeded is the staging
directory *promoted*: the previous output for that date (if any) is moved aside, the staging
directory is renamed into place, and the old one is deleted. Both renames are within one
filesystem, so each is atomic; the only window in which ``<root>/<date>`` is missing is between
them, and :func:`recover_interrupted_promotions` (run before every new run) puts the previous
output back if a crash happened exactly there. A run that fails — at any step — leaves its
staging directory behind for inspection at most, never touches ``<root>/<date>``, and never
touches the index: the last good report stays what readers see.

The index (``index.json`` + ``index.html``) lists the promoted runs, newest reference date
first, one entry per reference date (a re-run for the same date replaces its entry).

Concurrent runs. Two weekly runs on one output directory (a served deployment and a manual
``make forecast``) must not interleave their writes: promotion replaces ``<root>/<date>`` and
rewrites the index (a read-modify-write), so an interleaving could lose a run from the index or
promote one run's folder under another's record. :meth:`RunOutputs.staged` and
:meth:`RunOutputs.promote` therefore hold a per-directory file lock (``<root>/.run.lock``,
``filelock``; the kernel drops it if the holder dies): the second run's output phase waits for
the first one's, up to ``lock_timeout_s``, then fails naming the holder. The runs' computations
(minutes) still proceed side by side; their caches are safe under concurrency themselves.

Leftovers. Staging folders of killed runs are swept when they are more than a day old (a live
run's staging folder is minutes old).
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import html
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pipeline.data.california.counties import SAN_FRANCISCO
from pipeline.errors import ConfigError
from pipeline.io import STALE_AFTER_S, atomic_write_json, atomic_write_text, file_lock, sweep_stale

log = logging.getLogger(__name__)

INDEX_JSON = "index.json"
INDEX_HTML = "index.html"
RUN_RECORD = "run.json"
_STAGING_PREFIX = ".staging-"
_TRASH_PREFIX = ".previous-"
RUN_LOCK = ".run.lock"
RUN_LOCK_TIMEOUT_S = 600.0  # another run's output phase (render + promote) takes about a minute
_DATE_RE = re.compile(r"^\d{4}-\d{2}-\d{2}$")


@dataclasses.dataclass(frozen=True)
class RunRecord:
    """What the index says about one promoted run (also written as ``run.json`` in its folder)."""

    reference_date: str
    run_id: str
    finished_at: str
    data_stale: bool
    data_vintage: str
    model_key: str
    seed: int
    preset: str
    files: tuple[str, ...]
    summary: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["files"] = list(self.files)
        return out

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> RunRecord:
        fields = {f.name for f in dataclasses.fields(cls)}
        kwargs = {k: v for k, v in obj.items() if k in fields}
        kwargs["files"] = tuple(kwargs.get("files", ()))
        return cls(**kwargs)


def _check_date(reference_date: str) -> str:
    if not _DATE_RE.match(reference_date):
        raise ConfigError(f"reference date must be YYYY-MM-DD, got {reference_date!r}")
    dt.date.fromisoformat(reference_date)  # rejects 2022-02-30
    return reference_date


def new_run_id() -> str:
    """Sortable, unique: UTC timestamp plus 8 random hex digits."""
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    return f"{stamp}-{uuid.uuid4().hex[:8]}"


class RunOutputs:
    """The output root (e.g. ``reports/``): staging, promotion and the index of past runs."""

    def __init__(self, root: str | os.PathLike[str], *,
                 lock_timeout_s: float = RUN_LOCK_TIMEOUT_S, place: str = SAN_FRANCISCO) -> None:
        self.root = Path(root)
        self.place = place  # the index page's title names it
        self.lock_timeout_s = lock_timeout_s
        self._lock_depth = 0  # re-entrant: promote() runs inside staged()

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the output directory's run lock (re-entrant within this object)."""
        if self._lock_depth:
            self._lock_depth += 1
            try:
                yield
            finally:
                self._lock_depth -= 1
            return
        self.root.mkdir(parents=True, exist_ok=True)
        with file_lock(self.root / RUN_LOCK, timeout_s=self.lock_timeout_s,
                       what=f"output directory {self.root} (another weekly run is writing its "
                            f"report there)"):
            self._lock_depth = 1
            try:
                yield
            finally:
                self._lock_depth = 0

    # -- paths ---------------------------------------------------------------------------
    def final_dir(self, reference_date: str) -> Path:
        return self.root / _check_date(reference_date)

    def staging_dir(self, reference_date: str, run_id: str) -> Path:
        return self.root / f"{_STAGING_PREFIX}{_check_date(reference_date)}-{run_id}"

    # -- staging and promotion -----------------------------------------------------------
    def begin(self, reference_date: str, run_id: str | None = None) -> Path:
        """Create and return a fresh staging directory for a run on ``reference_date``."""
        self.root.mkdir(parents=True, exist_ok=True)
        with self.exclusive():
            recover_interrupted_promotions(self.root)
            for swept in sweep_stale(self.root, (f"{_STAGING_PREFIX}*",),
                                     older_than_s=STALE_AFTER_S):
                log.info("removed %s, a staging folder left by a run that died", swept)
        staging = self.staging_dir(reference_date, run_id or new_run_id())
        staging.mkdir(parents=False, exist_ok=False)
        return staging

    def promote(self, staging: Path, record: RunRecord) -> Path:
        """Make ``staging`` the output for ``record.reference_date`` and update the index.

        Writes ``run.json`` into the staging folder first, so a promoted folder always says
        what made it.
        """
        with self.exclusive():
            return self._promote(Path(staging), record)

    def _promote(self, staging: Path, record: RunRecord) -> Path:
        if not staging.is_dir() or staging.parent != self.root:
            raise ConfigError(f"not a staging directory of {self.root}: {staging}")
        atomic_write_json(staging / RUN_RECORD, record.to_json())
        final = self.final_dir(record.reference_date)
        trash = self.root / f"{_TRASH_PREFIX}{record.reference_date}-{record.run_id}"
        if final.exists():
            os.replace(final, trash)
        os.replace(staging, final)
        shutil.rmtree(trash, ignore_errors=True)
        self._write_index(record)
        log.info("promoted run %s to %s", record.run_id, final)
        return final

    def discard(self, staging: Path) -> None:
        """Remove a failed run's staging directory (the last good output is untouched)."""
        staging = Path(staging)
        if staging.parent == self.root and staging.name.startswith(_STAGING_PREFIX):
            shutil.rmtree(staging, ignore_errors=True)

    @contextlib.contextmanager
    def staged(self, reference_date: str, run_id: str | None = None) -> Iterator[Path]:
        """``with outputs.staged(date) as d: ...`` — discards ``d`` if the block raises.

        Holds the output directory's run lock for the block, so two runs' output phases
        (render, promote, index) never interleave. Promotion is explicit (:meth:`promote`)
        because the record is only known at the end.
        """
        with self.exclusive():
            staging = self.begin(reference_date, run_id)
            try:
                yield staging
            except BaseException:
                self.discard(staging)
                raise
            else:
                if staging.exists():  # the block did not promote it: nothing good came out
                    self.discard(staging)

    # -- index -----------------------------------------------------------------------------
    def runs(self) -> list[RunRecord]:
        """Promoted runs, newest reference date first (empty if there is no index yet)."""
        path = self.root / INDEX_JSON
        if not path.exists():
            return []
        try:
            payload = json.loads(path.read_text(encoding="utf-8"))
            return [RunRecord.from_json(r) for r in payload["runs"]]
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise ConfigError(f"damaged run index {path}: {exc}") from exc

    def latest(self) -> RunRecord | None:
        runs = self.runs()
        return runs[0] if runs else None

    def _write_index(self, record: RunRecord) -> None:
        runs = [r for r in self.runs() if r.reference_date != record.reference_date]
        runs.append(record)
        runs.sort(key=lambda r: (r.reference_date, r.finished_at), reverse=True)
        atomic_write_json(self.root / INDEX_JSON, {"runs": [r.to_json() for r in runs]})
        atomic_write_text(self.root / INDEX_HTML, render_index_html(runs, self.place))


def recover_interrupted_promotions(root: Path) -> list[Path]:
    """Put back a previous output whose replacement was interrupted between the two renames."""
    restored = []
    for trash in sorted(root.glob(f"{_TRASH_PREFIX}*")):
        reference_date = trash.name[len(_TRASH_PREFIX):len(_TRASH_PREFIX) + 10]
        final = root / reference_date
        if final.exists():
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(trash, final)
            restored.append(final)
            log.warning("restored %s after an interrupted promotion", final)
    return restored


def render_index_html(runs: list[RunRecord], place: str = SAN_FRANCISCO) -> str:
    """A small self-contained page linking every promoted run's report of ``place``."""
    rows = []
    for r in runs:
        date = html.escape(r.reference_date)
        report = next((f for f in r.files if f.endswith(".html")), None)
        link = f'<a href="{date}/{html.escape(report)}">{date}</a>' if report else date
        stale = "stale (cached data)" if r.data_stale else "fresh"
        # the report's page-1 headline in one line (pipeline.forecast.report.headline), when recorded
        headline = str((r.summary.get("headline") or {}).get("text", ""))
        rows.append(f"<tr><td>{link}</td><td>{html.escape(headline)}</td>"
                    f"<td>{html.escape(r.data_vintage)}</td><td>{stale}</td>"
                    f"<td>{html.escape(r.preset)}</td><td>{r.seed}</td>"
                    f"<td>{html.escape(r.finished_at)}</td></tr>")
    body = "\n".join(rows) or '<tr><td colspan="7">no runs yet</td></tr>'
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>flowcast weekly forecasts</title>
<style>body{{font-family:sans-serif;margin:2em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:left}}</style></head>
<body><h1>{html.escape(place)} weekly forecasts</h1>
<table><thead><tr><th>reference date</th><th>headline</th><th>data vintage</th><th>data</th>
<th>preset</th>
<th>seed</th><th>finished (UTC)</th></tr></thead>
<tbody>
{body}
</tbody></table></body></html>
"""
