"""Benchmarks: the workloads and records (``workloads``), their Markdown report
(``report``) and the CLI ``python -m jtus.bench`` (``__main__``)."""

from jtus.bench.report import markdown
from jtus.bench.workloads import (SIZES, bench_infer, bench_train, infer_workload, peaks,
                                  random_frame, random_window, torch_reference,
                                  train_workload)

__all__ = ["SIZES", "bench_infer", "bench_train", "infer_workload", "markdown", "peaks",
           "random_frame", "random_window", "torch_reference", "train_workload"]
