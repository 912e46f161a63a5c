"""Studies on many trials: one task per trial x mode x config on Dask (or in this process).

:mod:`~vio_graph.studies.engine` maps a function over task descriptions on a
``distributed.LocalCluster``, an existing Dask scheduler, or serially, isolating failures;
:mod:`~vio_graph.studies.grid` turns ``--set section.field=v1,v2`` options into validated
pipeline configs; :mod:`~vio_graph.studies.batch` is ``vio-graph batch``: the tasks, ``--resume``
and the summary (CSV, markdown, plot). ``evaluate``, ``compare`` and the sweep reach the same
engine through their ``--scheduler`` option.
"""
