"""The run: config (``config``), the frames into the tracker (``frames``), thread settings (``runtime``), the frame
loop, outputs and evaluation (``run``), what comes back (``result``).

``Pipeline(PipelineConfig.load(path, overrides)).run()`` is the Python API behind ``vslam run``.
"""

from vslam.data.config import DatasetConfig
from vslam.data.registry import open_dataset
from vslam.pipeline.config import OutputConfig, PipelineConfig
from vslam.pipeline.frames import prefetch, skipped_frames
from vslam.pipeline.result import RunResult
from vslam.pipeline.run import STAT_COLUMNS, Pipeline
from vslam.pipeline.runtime import blas_threads, torch_thread_count, torch_threads

__all__ = ["STAT_COLUMNS", "DatasetConfig", "OutputConfig", "Pipeline", "PipelineConfig", "RunResult", "blas_threads",
           "open_dataset", "prefetch", "skipped_frames", "torch_thread_count", "torch_threads"]
