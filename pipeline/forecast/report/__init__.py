"""The weekly run's report: its content built from the run's results
(:mod:`pipeline.forecast.results`) — page 2's headline (:mod:`.headline`), the model
diagnostics (:mod:`.diagnostics`) and the whole report (:mod:`.weekly`) — rendered by the
generic :mod:`pipeline.report` (typed content, figures, HTML and PDF)."""
