"""The CDC COVID-19 Forecast Hub's 53 locations: the US, the 50 states, DC and Puerto Rico.

Each with its postal abbreviation (what NHSN's ``jurisdiction`` column holds; the nation is
``USA`` there), its hub ``location`` code (two-digit state FIPS, ``US`` for the nation), its name
(what NSSP's ``geography`` column holds; the nation is "United States" there) and its population
as the hub's ``auxiliary-data/locations.csv`` gives it (CDCgov/covid19-forecast-hub, commit
8641100a4d0c1899c4a96fd90d56eb676af33853; ``../shared/data/nhsn/locations.csv``, checked against
this table by the tests). These populations are the known table the validation gate bounds every
location's counts by (:mod:`pipeline.data.core.gate`), never a figure read from a payload.

NHSN also publishes jurisdictions the hub does not forecast: the territories AS, GU, MP and VI
and the ten HHS regions (``Region 1`` … ``Region 10``); they are dropped as known non-hub places
(:data:`NOT_HUB_JURISDICTIONS`), while any other name is an unknown place and is skipped by the
gate, named.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class HubLocation:
    abbreviation: str   # NHSN jurisdiction (the nation: USA, see jurisdiction())
    location: str       # hub location code: two-digit FIPS, or US
    name: str
    population: int

    @property
    def jurisdiction(self) -> str:
        return "USA" if self.location == "US" else self.abbreviation


HUB_LOCATIONS: tuple[HubLocation, ...] = (
    HubLocation("US", "US", "US", 332_875_137),
    HubLocation("AL", "01", "Alabama", 4_903_185),
    HubLocation("AK", "02", "Alaska", 731_545),
    HubLocation("AZ", "04", "Arizona", 7_278_717),
    HubLocation("AR", "05", "Arkansas", 3_017_804),
    HubLocation("CA", "06", "California", 39_512_223),
    HubLocation("CO", "08", "Colorado", 5_758_736),
    HubLocation("CT", "09", "Connecticut", 3_565_287),
    HubLocation("DE", "10", "Delaware", 973_764),
    HubLocation("DC", "11", "District of Columbia", 705_749),
    HubLocation("FL", "12", "Florida", 21_477_737),
    HubLocation("GA", "13", "Georgia", 10_617_423),
    HubLocation("HI", "15", "Hawaii", 1_415_872),
    HubLocation("ID", "16", "Idaho", 1_787_065),
    HubLocation("IL", "17", "Illinois", 12_671_821),
    HubLocation("IN", "18", "Indiana", 6_732_219),
    HubLocation("IA", "19", "Iowa", 3_155_070),
    HubLocation("KS", "20", "Kansas", 2_913_314),
    HubLocation("KY", "21", "Kentucky", 4_467_673),
    HubLocation("LA", "22", "Louisiana", 4_648_794),
    HubLocation("ME", "23", "Maine", 1_344_212),
    HubLocation("MD", "24", "Maryland", 6_045_680),
    HubLocation("MA", "25", "Massachusetts", 6_892_503),
    HubLocation("MI", "26", "Michigan", 9_986_857),
    HubLocation("MN", "27", "Minnesota", 5_639_632),
    HubLocation("MS", "28", "Mississippi", 2_976_149),
    HubLocation("MO", "29", "Missouri", 6_626_371),
    HubLocation("MT", "30", "Montana", 1_068_778),
    HubLocation("NE", "31", "Nebraska", 1_934_408),
    HubLocation("NV", "32", "Nevada", 3_080_156),
    HubLocation("NH", "33", "New Hampshire", 1_359_711),
    HubLocation("NJ", "34", "New Jersey", 8_882_190),
    HubLocation("NM", "35", "New Mexico", 2_096_829),
    HubLocation("NY", "36", "New York", 19_453_561),
    HubLocation("NC", "37", "North Carolina", 10_488_084),
    HubLocation("ND", "38", "North Dakota", 762_062),
    HubLocation("OH", "39", "Ohio", 11_689_100),
    HubLocation("OK", "40", "Oklahoma", 3_956_971),
    HubLocation("OR", "41", "Oregon", 4_217_737),
    HubLocation("PA", "42", "Pennsylvania", 12_801_989),
    HubLocation("RI", "44", "Rhode Island", 1_059_361),
    HubLocation("SC", "45", "South Carolina", 5_148_714),
    HubLocation("SD", "46", "South Dakota", 884_659),
    HubLocation("TN", "47", "Tennessee", 6_829_174),
    HubLocation("TX", "48", "Texas", 28_995_881),
    HubLocation("UT", "49", "Utah", 3_205_958),
    HubLocation("VT", "50", "Vermont", 623_989),
    HubLocation("VA", "51", "Virginia", 8_535_519),
    HubLocation("WA", "53", "Washington", 7_614_893),
    HubLocation("WV", "54", "West Virginia", 1_792_147),
    HubLocation("WI", "55", "Wisconsin", 5_822_434),
    HubLocation("WY", "56", "Wyoming", 578_759),
    HubLocation("PR", "72", "Puerto Rico", 3_754_939),
)
US = "US"
BY_LOCATION: dict[str, HubLocation] = {h.location: h for h in HUB_LOCATIONS}
BY_JURISDICTION: dict[str, HubLocation] = {h.jurisdiction: h for h in HUB_LOCATIONS}
BY_NAME: dict[str, HubLocation] = {h.name.casefold(): h for h in HUB_LOCATIONS}
POPULATION: dict[str, int] = {h.location: h.population for h in HUB_LOCATIONS}
JURISDICTION_LOCATION: dict[str, str] = {j: h.location for j, h in BY_JURISDICTION.items()}
# NSSP names the nation "United States"; the hub, "US".
NAME_LOCATION: dict[str, str] = {**{n: h.location for n, h in BY_NAME.items()},
                                 "united states": "US"}
NOT_HUB_JURISDICTIONS: frozenset[str] = frozenset(
    {"AS", "GU", "MP", "VI", *(f"Region {k}" for k in range(1, 11))})


def hub_location(code: str) -> HubLocation:
    """The location of a hub code or a postal abbreviation (``06``, ``CA``, ``US``, ``USA``); an
    unknown one is a :class:`ConfigError` naming the closest."""
    text = code.strip()
    found = BY_LOCATION.get(text) or BY_JURISDICTION.get(text.upper()) or (
        BY_LOCATION[US] if text.upper() == US else None)
    if found is not None:
        return found
    known = [*BY_LOCATION, *BY_JURISDICTION]
    close = difflib.get_close_matches(text.upper(), known, n=3, cutoff=0.5)
    hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    raise ConfigError(f"unknown hub location {code!r}{hint}; the hub's 53 locations are US and "
                      f"the two-digit FIPS codes of the 50 states, DC and PR")
