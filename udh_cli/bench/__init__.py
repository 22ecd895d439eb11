"""``udh bench``: the paper's evaluation, every method side by side on the same pairs (see :mod:`.suite`)."""

from udh_cli.bench.metrics import FAIL_PX, Summary, summarize
from udh_cli.bench.report import BenchResult, check_output_folder, markdown_table, write_outputs
from udh_cli.bench.suite import run_pairs_bench, run_synthetic_bench

__all__ = ["FAIL_PX", "BenchResult", "Summary", "check_output_folder", "markdown_table", "run_pairs_bench", "run_synthetic_bench",
           "summarize", "write_outputs"]
