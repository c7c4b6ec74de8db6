"""The figures issue 39's release rules are stated against, measured on the real data
(``python -m bench.release_bounds`` -> ``bench/results/release_bounds.json``):

* ``lag_days``: per hub target, the days between a release's date and its newest week (the
  stale-release bound, :data:`pipeline.data.hub.release.MAX_LAG_DAYS`);
* ``national_fall``: the largest fall of the US row from one week to the next, over every week
  of every release and over each release's newest week (:data:`MAX_NATIONAL_FALL`);
* ``settled_revisions``: over consecutive releases, settled weeks (more than 28 days before the
  earlier release's last week) that went from 0 to positive (backfills), and the non-zero ones
  beyond the policy, by location and release;
* ``states_sum_over_us``: the 52 states' sum over the US row, in the newest release;
* ``cases_growth``: the fastest growth of 7-day case counts over the 7 days before (+ 100) in
  the six CDPH vintages and San Francisco's DataSF export (:class:`GrowthRule`).
"""
from __future__ import annotations

import glob
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.hub.nhsn_vintages import policy_of, target_spec
from pipeline.io import atomic_write_json

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RESULT = Path(__file__).parent / "results" / "release_bounds.json"


def _series(name: str) -> pd.DataFrame:
    t = pd.read_parquet(SHARED / name / "time-series.parquet")
    return t.assign(as_of=pd.to_datetime(t["as_of"].astype(str)),
                    target_end_date=pd.to_datetime(t["target_end_date"]))


def hub_figures(name: str) -> dict[str, object]:
    out: dict[str, object] = {}
    for target, g in _series(name).groupby("target"):
        g = g[g["observation"].notna()]
        releases = sorted(g["as_of"].unique())
        lags, falls, newest_falls = [], [], []
        for as_of, v in g.groupby("as_of"):
            lags.append(int((as_of - v["target_end_date"].max()).days))
            us = v[v["location"] == "US"].set_index("target_end_date")["observation"].sort_index()
            ratio = (us / us.shift(1))[us.shift(1) > 0]
            if len(ratio):
                falls.append((1 - float(ratio.min()), str(ratio.idxmin().date())))
                newest_falls.append((1 - float(ratio.iloc[-1]), str(pd.Timestamp(as_of).date())))
        policy = policy_of(target_spec(str(target)))
        backfills, beyond = [], []
        for a, b in zip(releases, releases[1:], strict=False):
            old, new = g[g["as_of"] == a], g[g["as_of"] == b]
            settled = old["target_end_date"].max() - pd.Timedelta(days=policy.open_days)
            m = old.merge(new, on=["target_end_date", "location"], suffixes=("", "_new"))
            m = m[m["target_end_date"] <= settled]
            before, after = m["observation"].to_numpy(), m["observation_new"].to_numpy()
            fill = (before == 0) & (after > 0)
            backfills += [(str(pd.Timestamp(b).date()), loc, float(x))
                          for loc, x in zip(m["location"][fill], after[fill], strict=True)]
            allowed = np.maximum(policy.settled_abs, policy.settled_rel * np.abs(before))
            bad = (before != 0) & (np.abs(after - before) > allowed)
            beyond += [(str(pd.Timestamp(b).date()), loc, str(w.date()), float(x), float(y))
                       for loc, w, x, y in zip(m["location"][bad], m["target_end_date"][bad],
                                               before[bad], after[bad], strict=True)]
        newest = g[g["as_of"] == g["as_of"].max()]
        wide = newest.pivot_table(index="target_end_date", columns="location",
                                  values="observation")
        states = wide.drop(columns="US").sum(axis=1, min_count=52) / wide["US"]
        out[str(target)] = {
            "releases": len(releases), "lag_days": sorted(set(lags)),
            "largest_national_fall": max(falls) if falls else None,
            "largest_national_fall_newest_week": max(newest_falls) if newest_falls else None,
            "settled_backfills": backfills, "settled_beyond_policy": beyond,
            "states_sum_over_us": [round(float(states.min()), 4),
                                   round(float(states.median()), 4),
                                   round(float(states.max()), 4)]}
    return out


def cases_growth(floor: float = 100.0) -> dict[str, object]:
    from pipeline.data.california.cdph import read_cdph_csv
    best: tuple[float, str, str, float, float] = (0.0, "", "", 0.0, 0.0)
    for path in sorted(glob.glob(str(SHARED / "cdph" / "*" / "covid19cases_test.csv"))):
        frame = read_cdph_csv(path).frame
        wide = frame.pivot_table(index="date", columns="area", values="cases").sort_index()
        now, before = wide.rolling(7).sum(), wide.rolling(7).sum().shift(7)
        ratio = (now / (before + floor)).stack()
        where = ratio.idxmax()
        if float(ratio.max()) > best[0]:
            best = (float(ratio.max()), str(pd.Timestamp(where[0]).date()), str(where[1]),
                    float(before.loc[where]), float(now.loc[where]))
    sf = pd.read_csv(next(iter(glob.glob(str(SHARED / "datasf" / "*" /
                                              "COVID-19_Cases_Over_Time.csv")))))
    daily = sf.assign(d=pd.to_datetime(sf["Specimen Collection Date"], format="mixed")
                      ).sort_values("d").set_index("d")["New Cases"]
    now, before = daily.rolling(7).sum(), daily.rolling(7).sum().shift(7)
    ratio = now / (before + floor)
    return {"floor": floor,
            "cdph": {"ratio": round(best[0], 2), "week_ending": best[1], "county": best[2],
                     "before": best[3], "after": best[4]},
            "san_francisco": {"ratio": round(float(ratio.max()), 2),
                              "week_ending": str(ratio.idxmax().date()),
                              "before": float(before[ratio.idxmax()]),
                              "after": float(now[ratio.idxmax()])}}


def main() -> int:
    result = {"nhsn": hub_figures("nhsn"), "flusight": hub_figures("flusight"),
              "cases_growth": cases_growth(), "command": "python -m bench.release_bounds"}
    for hub in ("nhsn", "flusight"):
        for target, f in result[hub].items():   # type: ignore[union-attr]
            print(f"{hub} {target}: {f['releases']} releases, lag {f['lag_days']} days, largest "
                  f"national fall {f['largest_national_fall']}, newest week "
                  f"{f['largest_national_fall_newest_week']}, {len(f['settled_backfills'])} "
                  f"backfills, beyond policy {f['settled_beyond_policy']}, states/US "
                  f"{f['states_sum_over_us']}")
    print("cases growth", result["cases_growth"])
    atomic_write_json(RESULT, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
