"""California's 58 counties: their names (as CDPH spells them), FIPS codes and folder names.

A county's FIPS code is the state's, ``06``, followed by the county's three-digit code: the odd
numbers 001, 003, … 115 in the alphabetical order of the 58 counties (Alameda 06001, Alpine 06003,
… San Francisco 06075, … Yuba 06115; U.S. Census Bureau, "FIPS codes for the states and
counties"). The names are CDPH's ``area`` values (``pipeline.data.california.cdph``).

Populations (:data:`COUNTY_POPULATION_2020`) are the 2020 Census counts (U.S. Census Bureau, 2020
Census Redistricting Data, P.L. 94-171, April 1, 2020), which sum to California's 39,538,223.
They are the known table the validation gate bounds every county's counts by
(:mod:`pipeline.data.core.gate`), never a figure read from a payload: CDPH's own ``population``
column (Department of Finance estimates) lies within 0.83–1.09× of them in every real vintage.
"""
from __future__ import annotations

import difflib
import re

from pipeline.errors import ConfigError

STATE_FIPS = "06"
SAN_FRANCISCO = "San Francisco"
COUNTIES: tuple[str, ...] = (
    "Alameda", "Alpine", "Amador", "Butte", "Calaveras", "Colusa", "Contra Costa", "Del Norte",
    "El Dorado", "Fresno", "Glenn", "Humboldt", "Imperial", "Inyo", "Kern", "Kings", "Lake",
    "Lassen", "Los Angeles", "Madera", "Marin", "Mariposa", "Mendocino", "Merced", "Modoc",
    "Mono", "Monterey", "Napa", "Nevada", "Orange", "Placer", "Plumas", "Riverside",
    "Sacramento", "San Benito", "San Bernardino", "San Diego", "San Francisco", "San Joaquin",
    "San Luis Obispo", "San Mateo", "Santa Barbara", "Santa Clara", "Santa Cruz", "Shasta",
    "Sierra", "Siskiyou", "Solano", "Sonoma", "Stanislaus", "Sutter", "Tehama", "Trinity",
    "Tulare", "Tuolumne", "Ventura", "Yolo", "Yuba")
CALIFORNIA_POPULATION_2020 = 39_538_223
COUNTY_POPULATION_2020: dict[str, int] = dict(zip(COUNTIES, (
    1_682_353, 1_204, 40_474, 211_632, 45_292, 21_839, 1_165_927, 27_743, 191_185, 1_008_654,
    28_917, 136_463, 179_702, 19_016, 909_235, 152_486, 68_163, 32_730, 10_014_009, 156_255,
    262_321, 17_131, 91_601, 281_202, 8_700, 13_195, 439_035, 138_019, 102_241, 3_186_989,
    404_739, 19_790, 2_418_185, 1_585_055, 64_209, 2_181_654, 3_298_634, 873_965, 779_233,
    282_424, 764_442, 448_229, 1_936_259, 270_861, 182_155, 3_236, 44_076, 453_491, 488_863,
    552_878, 99_633, 65_829, 16_112, 473_117, 55_620, 843_843, 216_403, 81_575), strict=True))
# The county codes are the odd numbers in alphabetical order (module docstring).
COUNTY_FIPS: dict[str, str] = {name: f"{STATE_FIPS}{2 * k + 1:03d}"
                               for k, name in enumerate(sorted(COUNTIES))}


def _folded(name: str) -> str:
    return " ".join(name.split()).casefold()


def california_county(name: str) -> str:
    """The county ``name`` as CDPH spells it (case and spacing ignored); an unknown name is a
    :class:`ConfigError` naming it, with the closest spellings."""
    by_folded = {_folded(c): c for c in COUNTIES}
    found = by_folded.get(_folded(name))
    if found is not None:
        return found
    close = difflib.get_close_matches(_folded(name), list(by_folded), n=3, cutoff=0.75)
    hint = (f"; did you mean {' or '.join(repr(by_folded[c]) for c in close)}?" if close
            else f"; the 58 counties are {', '.join(COUNTIES)}")
    raise ConfigError(f"unknown California county {name!r}{hint}")


def county_fips(name: str) -> str:
    """The five-digit FIPS code of a California county (e.g. ``"06075"`` for San Francisco)."""
    return COUNTY_FIPS[california_county(name)]


def county_slug(name: str) -> str:
    """The county's folder name: lower case, words joined by ``-`` (``"san-luis-obispo"``)."""
    return re.sub(r"[^a-z0-9]+", "-", california_county(name).lower()).strip("-")
