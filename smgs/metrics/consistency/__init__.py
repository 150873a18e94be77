"""RAFT-free view consistency (Softmax-GS Table 4, StopThePop's protocol)."""

from smgs.metrics.consistency.flow import (ESTIMATORS, Flow, backward_warp, border_mask,
                                           forward_backward_valid, geometric_flow, image_flow)
from smgs.metrics.consistency.score import (ConsistencyScores, PairScore, Table4Row, consistency_row,
                                            consistency_rows, score_consistency, mean_test_psnr)
from smgs.metrics.consistency.popping import (POP_METHODS, FlipScene, PopMethod, PopResult, flip_scenes,
                                              orbit_path, popping_table)
from smgs.data.trajectory import Trajectory, frame_pairs, interpolate_trajectory

__all__ = ["ESTIMATORS", "Flow", "backward_warp", "border_mask", "forward_backward_valid", "geometric_flow",
           "image_flow", "ConsistencyScores", "PairScore", "Table4Row", "consistency_row", "consistency_rows",
           "score_consistency", "mean_test_psnr",
           "POP_METHODS", "FlipScene", "PopMethod", "PopResult", "flip_scenes", "orbit_path", "popping_table", "Trajectory", "frame_pairs", "interpolate_trajectory"]
