"""Reading run directories: ``report`` writes ``results.json``, the plots and the significance tables of a run from
its ``run.json`` and raw metrics; ``statistics`` and ``continual_metrics`` hold the arithmetic, ``plots`` the
figures; ``reproduction`` compares a study with the paper's published numbers (``paper``)."""
