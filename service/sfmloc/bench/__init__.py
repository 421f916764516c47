"""``sfmloc bench``: the paper's Table 2 and Figures 2 and 4 on real and synthetic data, next to
the alternatives users would pick (single-image global matching on every frame, a pycolmap
SIFT pipeline), plus server throughput and map footprint. Entry point: ``main.main(conf, out)``.

Modules: ``config`` (suites, budgets), ``suites`` (data, maps, one run per suite), ``peers``
(single-image localizers over frames, timed like the engine), ``sift_peer`` (the SIFT map and
localizer), ``tune`` (the SIFT peer's tuning), ``throughput``, ``mapstats``, ``stats`` (Table 2
columns), ``figures`` (matplotlib, Agg), ``report`` (tables, report.md), ``readme`` (the
README's results block).
"""
