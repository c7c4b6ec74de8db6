"""Other teams' forecasts from a hubverse hub, and the hub's target data, as typed frames.

Sources:

* a collected file of quantile forecasts (``hub-forecasts.parquet`` of ``../shared/data/nhsn``:
  columns ``model_id, reference_date, target, horizon, location, target_end_date,
  output_type_id, value``, quantile rows only) — :func:`read_hub_forecasts`;
* a hub's ``model-output/<model_id>/<reference_date>-<model_id>.csv|parquet`` folder, as teams
  submit it — :func:`read_model_output_dir` (its quantile rows);
* the hub's ``target-data/time-series.parquet`` (``target_end_date, location, observation,
  as_of, target``: every vintage) — :func:`read_target_data` gives one vintage, the latest by
  default, as the truth frame ``target_end_date, location, value``;
* ``auxiliary-data/excluded_locations.toml`` (``"<reference_date>" = [locations]``) —
  :func:`read_excluded_locations`.

The typed long frame of quantile forecasts (:data:`QUANTILE_COLUMNS`): ``model_id``,
``target``, ``location`` categorical; ``reference_date``, ``target_end_date`` datetime64;
``horizon`` int64; ``output_type_id`` the quantile level (float64); ``value`` float64.
:func:`quantile_table` turns it into one row per forecast (a model's task) and a
(forecast × level) array, the form WIS is computed on.
"""
from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import DatasetError

TASK_COLUMNS: tuple[str, ...] = ("model_id", "reference_date", "target", "horizon", "location",
                                 "target_end_date")
QUANTILE_COLUMNS: tuple[str, ...] = (*TASK_COLUMNS, "output_type_id", "value")
TRUTH_COLUMNS: tuple[str, ...] = ("target_end_date", "location", "value")
_CATEGORICAL = ("model_id", "target", "location")
_DATES = ("reference_date", "target_end_date")
_MODEL_OUTPUT_FILE = re.compile(r"^(\d{4}-\d{2}-\d{2})-(.+)\.(csv|parquet)$")


class HubDataError(DatasetError):
    """A hub file (forecasts, target data, exclusions) that is missing or malformed."""


@dataclass(frozen=True, eq=False)
class QuantileTable:
    """Quantile forecasts one row per forecast: ``tasks`` (the :data:`TASK_COLUMNS`, one row
    per model × task), ``levels`` (Q,) increasing, ``values`` (len(tasks), Q)."""

    tasks: pd.DataFrame
    levels: np.ndarray
    values: np.ndarray


def _typed(table: pa.Table, source: object) -> pd.DataFrame:
    """Arrow columns → the typed long frame (dates parsed in arrow: 10x faster than pandas)."""
    missing = [c for c in QUANTILE_COLUMNS if c not in table.column_names]
    if missing:
        raise HubDataError(f"{source}: columns {missing} are missing (have {table.column_names})")
    columns: dict[str, pa.Array | pa.ChunkedArray] = {}
    for name in QUANTILE_COLUMNS:
        column = table.column(name)
        if name in _DATES:
            column = _as_timestamps(column)
        elif name in _CATEGORICAL:
            if not pa.types.is_dictionary(column.type):
                column = column.cast(pa.string()).dictionary_encode()
        elif name == "horizon":
            column = column.cast(pa.int64())
        else:
            column = column.cast(pa.float64())
        columns[name] = column
    frame = pa.table(columns).to_pandas()
    for name in _CATEGORICAL:
        frame[name] = _compact_categories(frame[name])
    if frame["value"].isna().any() or frame["output_type_id"].isna().any():
        row = int(np.flatnonzero((frame["value"].isna() | frame["output_type_id"].isna())
                                 .to_numpy())[0])
        raise HubDataError(f"{source}: a quantile row without a level or value: "
                           f"{frame.iloc[row].to_dict()}")
    return frame


def _compact_categories(column: pd.Series) -> pd.Series:
    """The categories a column uses, sorted (a filtered read keeps the file's whole dictionary,
    in file order); codes remapped with one lookup (pandas' own method is 10x slower)."""
    codes = column.cat.codes.to_numpy(dtype=np.int64)
    categories = np.asarray(column.cat.categories.astype(str))
    used = np.flatnonzero(np.bincount(codes[codes >= 0], minlength=categories.size))
    order = used[np.argsort(categories[used], kind="stable")]
    lookup = np.full(categories.size, -1, dtype=np.int64)
    lookup[order] = np.arange(order.size)
    remapped = np.where(codes >= 0, lookup[codes], -1)
    return pd.Series(pd.Categorical.from_codes(cast(Sequence[int], remapped),
                                               categories=categories[order].tolist()),
                     index=column.index, name=column.name)


def _as_timestamps(column: pa.ChunkedArray) -> pa.Array:
    """Dates (text ``YYYY-MM-DD`` or dates) as timestamps; a few hundred distinct dates repeat
    down millions of rows, so text is parsed once per distinct value."""
    if column.null_count:
        raise HubDataError(f"a date column has {column.null_count} empty cells")
    encoded = column.dictionary_encode().combine_chunks()
    distinct = pd.to_datetime(pd.Series(encoded.dictionary.to_pylist()).astype(str),
                              format="%Y-%m-%d").to_numpy(dtype="datetime64[s]")
    return pa.array(distinct[encoded.indices.to_numpy(zero_copy_only=False)])


def _filters(targets: Sequence[str] | None, horizons: Sequence[int] | None,
             models: Sequence[str] | None) -> list[tuple[str, str, list[object]]] | None:
    filters: list[tuple[str, str, list[object]]] = []
    if targets is not None:
        filters.append(("target", "in", list(targets)))
    if horizons is not None:
        filters.append(("horizon", "in", [int(h) for h in horizons]))
    if models is not None:
        filters.append(("model_id", "in", list(models)))
    return filters or None


def read_hub_forecasts(path: str | os.PathLike[str], *, targets: Sequence[str] | None = None,
                       horizons: Sequence[int] | None = None,
                       models: Sequence[str] | None = None) -> pd.DataFrame:
    """The quantile forecasts of a collected parquet file as the typed long frame, keeping only
    the given targets, horizons and models (filtered while reading)."""
    try:
        table = pq.read_table(path, columns=list(QUANTILE_COLUMNS),
                              filters=_filters(targets, horizons, models))
    except (OSError, pa.ArrowInvalid) as exc:
        raise HubDataError(f"cannot read hub forecasts {path}: {exc}") from exc
    return _typed(table, path)


def model_output_files(hub_dir: str | os.PathLike[str]) -> list[tuple[str, Path]]:
    """(model_id, path) of every ``model-output/<model_id>/<date>-<model_id>.csv|parquet``;
    a file whose name does not match its folder is an error."""
    root = Path(hub_dir) / "model-output"
    if not root.is_dir():
        raise HubDataError(f"{hub_dir}: no model-output/ folder")
    found = []
    for path in sorted(root.glob("*/*")):
        match = _MODEL_OUTPUT_FILE.match(path.name)
        if match is None:
            continue  # READMEs and the like, as hubverse tools skip them
        if match.group(2) != path.parent.name:
            raise HubDataError(f"{path}: model id {match.group(2)!r} in the file name differs "
                               f"from its folder {path.parent.name!r}")
        found.append((path.parent.name, path))
    return found


def _read_model_output_file(path: Path) -> pa.Table:
    try:
        if path.suffix == ".parquet":
            table = pq.read_table(path)
        else:  # every cell as text first: sample ids and levels share output_type_id
            frame = pd.read_csv(path, dtype=str, keep_default_na=False)
            table = pa.Table.from_pandas(frame, preserve_index=False)
    except (OSError, ValueError, pa.ArrowInvalid, pd.errors.ParserError) as exc:
        raise HubDataError(f"cannot read model-output file {path}: {exc}") from exc
    if "output_type" not in table.column_names:
        raise HubDataError(f"{path}: no output_type column")
    kinds = table.column("output_type").cast(pa.string()).to_numpy(zero_copy_only=False)
    quantile = table.filter(pa.array(kinds == "quantile"))
    try:
        return quantile.set_column(quantile.column_names.index("output_type_id"), "output_type_id",
                                   quantile.column("output_type_id").cast(pa.float64()))
    except (pa.ArrowInvalid, ValueError) as exc:
        raise HubDataError(f"{path}: a quantile output_type_id is not a number ({exc})") from exc


def read_model_output_dir(hub_dir: str | os.PathLike[str], *,
                          models: Sequence[str] | None = None) -> pd.DataFrame:
    """The quantile rows of every model-output file of a hub (``model_id`` from the folder,
    as hubverse partitions it) as the typed long frame."""
    tables = []
    for model_id, path in model_output_files(hub_dir):
        if models is not None and model_id not in models:
            continue
        table = _read_model_output_file(path)
        keep = [c for c in QUANTILE_COLUMNS if c != "model_id" and c in table.column_names]
        table = table.select(keep)
        for name in table.column_names:  # one type per column whatever each file inferred
            if name != "output_type_id":
                table = table.set_column(table.column_names.index(name), name,
                                         table.column(name).cast(pa.string()))
        tables.append(table.append_column("model_id",
                                          pa.array([model_id] * table.num_rows, pa.string())))
    if not tables:
        raise HubDataError(f"{hub_dir}: no model-output file" +
                           (f" of the models {list(models)}" if models is not None else ""))
    return _typed(pa.concat_tables(tables, promote_options="permissive"), hub_dir)


def _task_codes(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """0..n-1 numbering the distinct tasks in the order of :data:`TASK_COLUMNS` (each column
    coded, the codes combined in mixed radix: no sort of the rows' tuples), and the first row
    of each task."""
    key = np.zeros(len(frame), dtype=np.int64)
    for name in TASK_COLUMNS:
        column = frame[name]
        if isinstance(column.dtype, pd.CategoricalDtype):
            codes, size = column.cat.codes.to_numpy(dtype=np.int64), len(column.cat.categories)
        else:
            codes, uniques = pd.factorize(column, sort=True)
            size = len(uniques)
        key = key * max(size, 1) + codes
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return inverse.astype(np.int64).ravel(), first


def quantile_table(frame: pd.DataFrame) -> QuantileTable:
    """One row per forecast and its values at every level (the levels found in the frame):
    vectorized scatter, no sort of the long frame. Every forecast must have each level once."""
    if frame.empty:
        raise HubDataError("no quantile forecasts to tabulate")
    levels = np.unique(frame["output_type_id"].to_numpy(dtype=np.float64))
    task, first = _task_codes(frame)
    level = np.searchsorted(levels, frame["output_type_id"].to_numpy(dtype=np.float64))
    n_tasks, n_levels = int(task.max()) + 1, levels.size
    cell = task * n_levels + level
    counts = np.bincount(cell, minlength=n_tasks * n_levels).reshape(n_tasks, n_levels)
    tasks = frame[list(TASK_COLUMNS)].iloc[first].reset_index(drop=True)
    wrong = np.flatnonzero((counts != 1).any(axis=1))
    if wrong.size:
        k = int(wrong[0])
        have = levels[counts[k] > 0].tolist()
        raise HubDataError(f"forecast {tasks.iloc[k].to_dict()}: each of the {n_levels} levels "
                           f"{levels.tolist()} must appear once; it has {have} "
                           f"(counts {counts[k].tolist()}); {wrong.size} forecasts are affected")
    values = np.empty(n_tasks * n_levels)
    values[cell] = frame["value"].to_numpy(dtype=np.float64)
    return QuantileTable(tasks=tasks, levels=levels, values=values.reshape(n_tasks, n_levels))


def target_data_vintages(path: str | os.PathLike[str], target: str) -> list[pd.Timestamp]:
    """The ``as_of`` dates of a hub time series that hold ``target``, oldest first."""
    frame = _read_time_series(path, target)
    return sorted(pd.to_datetime(frame["as_of"]).unique())


def _read_time_series(path: str | os.PathLike[str], target: str) -> pd.DataFrame:
    columns = ["target_end_date", "location", "observation", "as_of", "target"]
    try:
        table = pq.read_table(path, columns=columns, filters=[("target", "=", target)])
    except (OSError, pa.ArrowInvalid) as exc:
        raise HubDataError(f"cannot read hub target data {path}: {exc}") from exc
    frame = table.to_pandas()
    if frame.empty:
        raise HubDataError(f"{path}: no rows of the target {target!r}")
    return frame


def read_target_data(path: str | os.PathLike[str], target: str,
                     as_of: str | pd.Timestamp | None = None) -> pd.DataFrame:
    """One vintage of a hub's ``time-series.parquet`` for ``target``: the truth frame
    ``target_end_date`` (datetime64), ``location`` (str), ``value`` (float64). ``as_of=None``
    takes the latest vintage, what a hub scores forecasts against."""
    frame = _read_time_series(path, target)
    stamps = pd.to_datetime(frame["as_of"])
    wanted = stamps.max() if as_of is None else pd.Timestamp(as_of)
    rows = frame[(stamps == wanted).to_numpy()]
    if rows.empty:
        raise HubDataError(f"{path}: no vintage as_of {wanted.date()} of {target!r} (vintages "
                           f"{stamps.min().date()} .. {stamps.max().date()})")
    truth = pd.DataFrame({"target_end_date": pd.to_datetime(rows["target_end_date"])
                          .astype("datetime64[s]").to_numpy(),
                          "location": rows["location"].astype(str).to_numpy(),
                          "value": rows["observation"].to_numpy(dtype=np.float64)})
    if truth.duplicated(["target_end_date", "location"]).any():
        raise HubDataError(f"{path}: vintage {wanted.date()} of {target!r} has a week counted "
                           "twice for one location")
    return truth.sort_values(["location", "target_end_date"]).reset_index(drop=True)


def read_excluded_locations(path: str | os.PathLike[str]) -> pd.DataFrame:
    """``excluded_locations.toml`` as a frame ``reference_date`` (datetime64), ``location``."""
    try:
        spec = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise HubDataError(f"cannot read excluded locations {path}: {exc}") from exc
    pairs = []
    for reference_date, locations in spec.items():
        if not isinstance(locations, list):
            raise HubDataError(f"{path}: {reference_date!r} must list locations, got "
                               f"{locations!r}")
        pairs += [(reference_date, str(location)) for location in locations]
    frame = pd.DataFrame(pairs, columns=["reference_date", "location"])
    try:
        frame["reference_date"] = pd.to_datetime(frame["reference_date"], format="%Y-%m-%d") \
            .astype("datetime64[s]")
    except ValueError as exc:
        raise HubDataError(f"{path}: a key is not a date YYYY-MM-DD ({exc})") from exc
    return frame
