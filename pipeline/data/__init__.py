"""The real data the forecasts read: one subpackage per source, over a core every source shares.

* ``core`` — how a payload arrives, is decoded, checked and kept, for every source (bounded HTTP
  transport, SODA pager, decode boundary, live-with-cache fallback, the cache and its vintages,
  the validation gate and its plausibility rule) and the S/I/R counts of a place;
* ``sf`` — San Francisco from DataSF: the client, CSV import, validation, revision policy, the
  combined daily series and its S/I/R conversion;
* ``california`` — California's counties from CDPH: the county table, the CHHS portal client,
  the county file, its source with every vintage kept, and the reporting-delay model fitted from
  those vintages;
* ``hub`` — the CDC COVID-19 Forecast Hub: its 53 locations, NHSN admissions and NSSP ED shares
  as vintages, imports of a hub's target data, other teams' forecasts.
"""
