"""The hyper-parameter search of the neural models (thesis Sec. 4.2.5, Tables I and II): ``daror hpsearch``.

The thesis searched PENN and NNN over layers, width, activation, L1 rate, inputs and two
initialisations (864 networks, days of training); this package runs the same grid in minutes on
two cores (docs/hpsearch.md):

* :mod:`.grid`: the grid (:class:`~.grid.SearchGrid`), the built-in ``thesis`` and ``small`` grids,
  a grid from YAML;
* :mod:`.work`: the work unit (one network shape, all its lambdas and seeds in one
  :func:`~daror_runtime.neural.training.train_group` call) and what a worker does with it;
* :mod:`.executors`: local worker processes, or Ray tasks (the optional extra ``ray``);
* :mod:`.search`: :func:`~.search.run_search`, the grid cut into units, most expensive first;
* :mod:`.report`: ``networks.csv``, ``ranking.csv``, ``ranking.md`` and ``summary.json``.
"""
