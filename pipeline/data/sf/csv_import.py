"""DataSF full CSV exports (``/api/views/<id>/rows.csv?accessType=DOWNLOAD``) -> the cache.

Exports use display column names ("Specimen Collection Date", "New Cases", ...), US timestamps
("03/04/2020 12:00:00 AM") and unsorted rows; the tests export mixes API names with slash-ISO
dates ("2020/03/02"). Which dataset a file holds is decided by its columns (the spec whose
required fields and vintage stamps it matches best; ties or no date column -> error), never by
the file name, since archived exports are often renamed. Every known header style is read: display
names, API names as headers, and the later testing export (``DATE, tests, pos, neg, indet``);
an unknown one fails naming the columns it has and the ones each dataset needs.

``import_csv_exports`` validates *every* file before storing any, so a failed import changes
nothing in the cache. A file that would replace the cached copy with a shorter, older or
rewritten series is refused like a live payload (:mod:`pipeline.data.sf.revisions`) unless
``accept_revisions``. ``if_empty`` imports datasets the cache lacks *or holds damaged* (an
unreadable manifest, a missing or altered payload, data that no longer validate): a damaged
dataset is repaired, not skipped.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.data.core.cache import DatasetCache
from pipeline.data.sf.datasf import DATASETS, DatasetSpec, check_gate
from pipeline.data.core.decoding import decode_boundary
from pipeline.data.sf.payloads import decode_cached, read_csv_bytes
from pipeline.data.sf.revisions import commit_validated
from pipeline.data.sf.validation import (GapPolicy, ValidatedFrame, find_column, column_match_count,
                                         validate_frame)
from pipeline.errors import DataSourceError, ValidationError

__all__ = ["ImportSummary", "detect_dataset", "import_csv_exports", "read_csv_bytes",
           "validate_csv_export"]


@dataclass(frozen=True)
class ImportSummary:
    path: Path
    dataset_key: str
    dataset_id: str
    row_count: int
    first_date: str
    last_date: str
    final_cumulative: int | None
    data_as_of: str | None
    imported: bool                 # False when skipped by --if-empty
    warnings: tuple[str, ...] = ()
    note: str = ""


def detect_dataset(columns: Sequence[str], *, source: str) -> DatasetSpec:
    """The spec whose fields ``columns`` match best.

    A candidate must carry its date column *and* at least one of its count columns: a shared
    date name ("Specimen Collection Date") plus a vintage stamp is not enough, otherwise other
    DataSF exports (e.g. tvq9-ec9w, cases by transmission) would be taken for the tests dataset
    and fail with a misleading list of "missing" columns. One renamed count column (``New
    Kases``) still identifies the cases export by its other columns, so its error names the
    missing field.
    """
    scored = sorted(((column_match_count(columns, s), s) for s in DATASETS.values()
                     if find_column(columns, s.date) is not None
                     and any(find_column(columns, f) is not None
                             for f in s.required if f is not s.date)),
                    key=lambda pair: pair[0], reverse=True)
    if not scored or scored[0][0] < 2 or (len(scored) > 1 and scored[0][0] == scored[1][0]):
        known = "; ".join(f"{s.key} ({s.dataset_id}): "
                          + ", ".join(f"'{f.display}'" for f in s.required)
                          + " (also read as " + ", ".join(
                              "|".join(dict.fromkeys(n for n in (f.api, *f.aliases)
                                                     if n != f.display))
                              for f in s.required) + ")"
                          for s in DATASETS.values())
        raise ValidationError(f"{source}: cannot tell which DataSF dataset this is from its "
                              f"columns {list(columns)}; expected one of — {known}")
    return scored[0][1]


def validate_csv_export(path: str | os.PathLike[str], *,
                        gap_policy: GapPolicy = GapPolicy.ZERO_FILL
                        ) -> tuple[ValidatedFrame, bytes]:
    """Read, detect and validate one export; returns the validated frame and the raw bytes."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataSourceError(f"cannot read {path}: {exc}") from exc
    raw = read_csv_bytes(data, source=str(path))
    spec = detect_dataset(list(raw.columns), source=str(path))
    with decode_boundary("CSV export", str(path), len(data)):
        validated = validate_frame(raw, spec, source=str(path), gap_policy=gap_policy)
    # Here, not only at commit: every file passes every check before any is stored.
    check_gate(validated.frame, spec, source=str(path))
    return validated, data


def import_csv_exports(paths: Sequence[str | os.PathLike[str]],
                       data_dir: str | os.PathLike[str] | None = None, *,
                       if_empty: bool = False, accept_revisions: bool = False,
                       gap_policy: GapPolicy = GapPolicy.ZERO_FILL) -> list[ImportSummary]:
    """Validate every file, then store each into the cache (``if_empty``: only datasets the
    cache lacks or holds damaged). Two files of the same dataset in one call are refused (which
    one wins?)."""
    cache = DatasetCache.default(data_dir)
    checked = [(Path(p), *validate_csv_export(p, gap_policy=gap_policy)) for p in paths]
    keys = [v.spec.key for _, v, _ in checked]
    duplicates = sorted({k for k in keys if keys.count(k) > 1})
    if duplicates:
        raise ValidationError(f"several files hold the same dataset ({', '.join(duplicates)}); "
                              f"import one export per dataset")
    summaries = []
    for path, validated, data in checked:
        spec, report = validated.spec, validated.report
        as_of = report.data_as_of.isoformat() if report.data_as_of is not None else None
        damage = cache_damage(cache, spec, gap_policy) if if_empty else None
        skip = if_empty and damage is None and cache.has(spec)
        if not skip:
            # A damaged copy is no reference for the successor checks: replace it outright.
            commit_validated(cache, validated, data, suffix="csv", source_kind="csv-import",
                             source=str(path.resolve()), gap_policy=gap_policy,
                             accept_revisions=accept_revisions or damage is not None)
        note = ("cache already holds this dataset; left as is (--if-empty)" if skip else
                f"repaired a damaged cache: {damage}" if damage else "")
        summaries.append(ImportSummary(
            path=path, dataset_key=spec.key, dataset_id=spec.dataset_id,
            row_count=report.row_count, first_date=str(report.first_date.date()),
            last_date=str(report.last_date.date()), final_cumulative=report.final_cumulative,
            data_as_of=as_of, imported=not skip, warnings=report.warnings, note=note))
    return summaries


def cache_damage(cache: DatasetCache, spec: DatasetSpec, gap_policy: GapPolicy) -> str | None:
    """Why the cached copy of ``spec`` is unusable (None: absent or fine)."""
    cached, damage = cache.load_or_damage(spec)
    if damage is not None or cached is None:
        return damage
    try:
        validate_frame(decode_cached(cached), spec, source=str(cached.path),
                       gap_policy=gap_policy)
    except DataSourceError as exc:
        return str(exc)
    return None
