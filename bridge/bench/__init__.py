"""``hilbo bench``: the benchmarks (Kim et al. 2019's stopping study, simulated HIL sessions, latency).

Modules: :mod:`~bridge.bench.stopping`, :mod:`~bridge.bench.hil`, :mod:`~bridge.bench.perf`
(the three benchmarks), :mod:`~bridge.bench.executors` (local processes or Dask),
:mod:`~bridge.bench.plots`, :mod:`~bridge.bench.cli` (``add_bench_parser``).
"""

__all__: list[str] = []
