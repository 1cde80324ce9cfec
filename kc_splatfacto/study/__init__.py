"""Studies: many training runs (scenes x methods x seeds) planned, executed serially or as Ray tasks, and resumed
(``kc-bench`` is the command; :mod:`kc_splatfacto.analysis.report` makes the report)."""
