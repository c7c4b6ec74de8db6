"""DataSF full CSV exports (``/api/views/<id>/rows.csv?accessType=DOWNLOAD``) -> the cache.

Exports use display column names ("Specimen Collection Date", "New Cases", ...), US timestamps
("03/04/2020 12:00:00 AM") and unsorted rows; the tests export mixes API names with slash-ISO
dates ("2020/03/02"). Which dataset a file holds is decided by its columns (the spec whose
required fields and vintage stamps it matches best; ties or no date column -> error), never by
the file name, since archived exports are often renamed.

``import_csv_exports`` validates *every* file before storing any, so a failed import changes
nothing in the cache.
"""
from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.data.cache import DatasetCache
from pipeline.data.datasf import DATASETS, DatasetSpec
from pipeline.data.validation import (GapPolicy, ValidatedFrame, find_column,
                                      column_match_count, validate_frame)
from pipeline.errors import DataSourceError, ValidationError


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


def read_csv_bytes(data: bytes, *, source: str) -> pd.DataFrame:
    """All cells as strings (so validation sees exactly what the file says)."""
    if not data.strip():
        raise ValidationError(f"{source}: empty file")
    try:
        return pd.read_csv(io.BytesIO(data), dtype=str, keep_default_na=False,
                           na_values=[""], skipinitialspace=True)
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
        raise ValidationError(f"{source}: not a readable CSV: {exc}") from exc


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
    return validate_frame(raw, spec, source=str(path), gap_policy=gap_policy), data


def import_csv_exports(paths: Sequence[str | os.PathLike[str]],
                       data_dir: str | os.PathLike[str] | None = None, *,
                       if_empty: bool = False,
                       gap_policy: GapPolicy = GapPolicy.ZERO_FILL) -> list[ImportSummary]:
    """Validate every file, then store each into the cache (``if_empty``: only datasets the
    cache lacks). Two files of the same dataset in one call are refused (which one wins?)."""
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
        skip = if_empty and cache.has(spec)
        if not skip:
            cache.store(spec, data, suffix="csv", source_kind="csv-import",
                        source=str(path.resolve()), row_count=report.row_count,
                        first_date=str(report.first_date.date()),
                        last_date=str(report.last_date.date()), data_as_of=as_of,
                        final_cumulative=report.final_cumulative)
        summaries.append(ImportSummary(
            path=path, dataset_key=spec.key, dataset_id=spec.dataset_id,
            row_count=report.row_count, first_date=str(report.first_date.date()),
            last_date=str(report.last_date.date()), final_cumulative=report.final_cumulative,
            data_as_of=as_of, imported=not skip, warnings=report.warnings,
            note="cache already holds this dataset; left as is (--if-empty)" if skip else ""))
    return summaries
