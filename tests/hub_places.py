"""The hub locations the end-to-end round tests run on when their point is per location (a
member that fails, a revision held, a stale target): the nation and a dozen states of every
size and region, Missouri among them (no ED share). A round's cost grows with its locations;
what it does at each is the same at 13 as at 53, and one test (tests/test_hub_forecast.py)
keeps the hub's whole set."""
from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

PLACES = ("US", "06", "48", "12", "36", "17", "13", "53", "04", "29", "31", "50", "02")


def only_places(series: pd.DataFrame, places: Sequence[str] = PLACES) -> pd.DataFrame:
    """The rows of a hub time series (``location`` column) at ``places``."""
    return series[series["location"].isin(places)]
