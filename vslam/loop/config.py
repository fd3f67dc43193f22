"""Settings of loop closing and place-recognition relocalisation (``slam.loop`` in a config)."""

from __future__ import annotations

from dataclasses import dataclass, field

from vslam.backend.pose_graph import PoseGraphConfig


@dataclass(frozen=True)
class LoopConfig:
    # Loop detection + correction per keyframe, place-recognition relocalisation. Off by default: it accepted
    # no false loop on KITTI 07 and TUM teddy and left their poses bit-identical, but the other synthetic / VIO /
    # line rows were not re-checked and it is costly per keyframe, mostly the verification of candidates
    # (docs/loop.md, "LoopConfig").
    enabled: bool = False
    descriptor: str = "bow"  # key of make_place_descriptor: bow | vladnet
    vocabulary: str = ""  # vocabulary file; "" = vslam/models/orb_bow_k512.npz
    weights: str = ""  # VLADNet weights; "" = vslam/models/vladnet_v1.pt
    # -- detection (ORB-SLAM LoopClosing::DetectLoop) --
    top_k: int = 5  # database candidates per keyframe
    min_score: float = 0.05  # absolute floor on the descriptor similarity
    min_kf_gap: int = 10  # a candidate is at least this many keyframes older than the query
    consistency: int = 2  # consecutive keyframes whose candidate covisibility groups must agree
    group_min_shared: int = 15  # covisibility of a candidate's group
    # -- geometric verification --
    min_matches: int = 40  # descriptor matches to the candidate's local map before RANSAC
    min_pnp_inliers: int = 30
    min_inliers: int = 60  # after guided matching and robust refinement: accepted loop
    ratio: float = 0.8
    max_hamming: int = 64
    ransac_px: float = 3.0
    guided_radius_px: float = 4.0
    local_keyframes: int = 10  # candidate + its most covisible keyframes form the map it is verified against
    max_std_m: float = 0.015  # verified pose must be this well constrained (first-order position std, metres)
    max_correction_m: float = 3.0  # larger translation corrections are refused (a verified yet absurd loop)
    # -- correction --
    covis_edge_min: int = 100  # pose-graph edges between keyframes sharing this many points (+ consecutive ones)
    fuse_neighbors: int = 10  # loop-side map points are fused into the query keyframe and this many neighbours
    local_ba: bool = True  # local BA around the query keyframe after fusion (when global_ba is off)
    global_ba: bool = True  # BA over the whole map after each corrected loop (ORB-SLAM runs it after the pose graph)
    global_ba_iterations: int = 10
    # Keyframes observing fewer map points than this keep their pose-graph pose in global BA: a pose seen
    # through 3 points is not determined by them (on the 2-loop lighting route such keyframes were thrown far
    # off, their frames with them, and loop closing made the ATE worse before this rule; docs/loop.md,
    # "LoopConfig")
    global_ba_min_obs: int = 20
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    # monocular loops are corrected as similarities (Sim3 essential graph); False: detected and verified only
    mono_sim3: bool = True
    sim3_min_points: int = 20  # keypoints with a point on both sides needed to measure the loop's scale
    sim3_sigma_scale: float = 0.01  # per-edge std of log-scale in the Sim3 graph
    # -- relocalisation after tracking loss --
    relocalise: bool = True
    reloc_top_k: int = 5
    seed: int = 0
