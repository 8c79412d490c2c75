"""What carries the nodes: the ``Cell`` protocol the runner drives and the choice of
transport (``cell``); every node in one process (``inproc``); or each in its own process
over Zenoh (``zenoh_cell``, ``launch``, ``process``, ``service``, ``subscriptions``,
``session``), on hosts in network namespaces (``hosts``), with the run's credentials
(``credentials``); a service process keeps its garbage collector out of its cycles
(``collector``) and can profile itself (``profiling``)."""
