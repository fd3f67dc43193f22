"""How a run uses the machine: threads, the front-end process, its workers (``runtime:`` of a run config).

None of these changes what is computed (the same trajectory bytes, except ``torch_threads``: see there), only how
fast; so they live apart from the algorithm's settings (``slam:``), and a benchmark compares them by timing alone.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RuntimeConfig:
    # Keypoints, line segments, keypoint depth and detector boxes depend on the image alone: ``vslam run``
    # computes them for the next frames on its prefetch thread while this one is tracked (OpenCV / torch release
    # the GIL, so it uses a second core). Same numbers either way; off = everything on the tracking thread.
    frontend_thread: bool = True
    # With frontend_thread: decode the frames and run that front end in a child process instead of a thread
    # (``vslam.tracking.frontend_process``: GTSAM's BA holds the GIL, and a thread cannot work ahead through it).
    # The same numbers bit for bit; faster where the front end is what tracking waits for (TUM teddy ORB-only, the
    # learned pipeline). The child's start counts too: on short subsets it costs more than it saves
    # (docs/speed.md). A sequence that cannot be pickled to the
    # child runs on the thread.
    frontend_process: bool = True
    # With frontend_process: frames whose front end the child makes at once, a thread and a tracker each, while
    # another thread reads the sequence. A frame's front end depends on its images alone, so the numbers are the
    # same for any count. Where tracking is light the front end is what it waits for (EuRoC stereo), and one
    # frame at a time left a core idle. 0 = 2 for stereo without a network where the process may use 2+ CPUs,
    # else 1 (an RGB-D front end keeps ahead alone; torch's threads already spread a network over the cores);
    # ``frontend_process.frame_workers``; timings in docs/speed.md.
    frontend_workers: int = 0
    # LSD segments on a thread of their own, beside the networks: on a GPU LSD (CPU) takes longer than
    # ConvPoint or the detector (docs/speed.md), so in a row the front end costs their sum, side by side the
    # longest. None = when the keypoint network runs on CUDA (the 2-core CPU target has no core to
    # spare); the same segments either way.
    lines_beside_networks: bool | None = None
    # Intra-op threads of the networks (torch) while a run lasts; 0 = the CPUs this process may use,
    # less one for the tracking thread when the front end has its own. torch's default (every core) put three
    # busy threads on the 2-core VM and slowed the learned pipeline (docs/speed.md).
    # The thread count changes float summation order, hence trajectories a little (docs/speed.md).
    torch_threads: int = 0
    # numpy's BLAS (OpenBLAS) threads while a run lasts (and in the BA worker process); 0 = its default
    # (every core). Its matrices here are small (BA windows, batched 4x4 line solves): a second OpenBLAS thread
    # spins beside them and takes the core the front-end thread needs: with lines, local BA spent more than
    # twice the CPU with it (docs/lines.md). Same trajectories byte for byte.
    blas_threads: int = 1


# run-config keys that moved here from ``slam:`` (a config that still has them is told where they went)
MOVED_KEYS = {f"slam.{k}": f"runtime.{k}" for k in ("frontend_thread", "frontend_process", "frontend_workers",
                                                   "lines_beside_networks", "torch_threads", "blas_threads")}
