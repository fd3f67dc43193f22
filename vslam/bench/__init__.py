"""`vslam bench`: run a suite of (config, sequence) rows and rewrite BENCHMARKS.md.

Each run happens in a fresh spawned process so its peak memory is its own and one row cannot warm caches for the
next. Timings are only compared as ratios inside one BENCHMARKS.md (same machine, same run). ``--jobs N`` /
``--ray`` run the jobs in parallel (``batch``): the same metrics, timings no longer clean. ``--sweep KEY=V1,V2``
runs every selected row once per value (a parameter sweep).

The measured numbers live in a machine-readable sidecar next to the Markdown (``BENCHMARKS.json`` beside
``BENCHMARKS.md``): ``--only NAME`` re-measures those rows, keeps every other row from the sidecar and re-renders
the whole file, with the date each row was measured. Parsing the Markdown back would break with every change of
its layout; the JSON does not.

Modules: ``suite`` (rows, sidecar), ``kinds`` (one module per kind: its job and its table), ``jobs`` (a job in a
fresh process), ``run`` (``run_bench``), ``render`` (BENCHMARKS.md, ``--check``), ``checks`` (targets as machine
checks), ``batch`` (parallel passes, A/B rows), ``tables`` (Markdown pieces).
"""

from vslam.bench.jobs import execute_job, machine_info, run_job
from vslam.bench.render import check_bench, render_bench, render_markdown, write_readme_table
from vslam.bench.run import run_bench
from vslam.bench.suite import BenchRow, BenchSuite, load_sidecar, load_suite, sidecar_path

__all__ = ["BenchRow", "BenchSuite", "check_bench", "execute_job", "load_sidecar", "load_suite", "machine_info",
           "render_bench", "render_markdown", "run_bench", "run_job", "sidecar_path", "write_readme_table"]
