"""``python -m bridge.bench stopping|hil|perf ...`` (the same as ``hilbo bench ...``)."""

import sys

from bridge.bench.cli import bench_main

__all__: list[str] = []

sys.exit(bench_main())
