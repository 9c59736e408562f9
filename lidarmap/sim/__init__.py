"""The simulator: a procedural city scanned by simulated aerial and mobile LiDAR, with exact ground truth.

``simulate(out_dir, params)`` writes what real acquisitions deliver (LAZ, trajectories, footprints) plus the
truth under ``out_dir/truth``; ``load_truth(out_dir)`` reads that truth back. See docs/simulator.md.
"""

from lidarmap.sim.city import City, build_city
from lidarmap.sim.params import SimParams
from lidarmap.sim.scene import SimResult, simulate
from lidarmap.sim.truth import (
                                PointTruth,
                                SimTruth,
                                TruthBuilding,
                                TruthCampaign,
                                TruthElement,
                                TruthFacade,
                                load_ply,
                                load_truth,
)

__all__ = ["City", "PointTruth", "SimParams", "SimResult", "SimTruth", "TruthBuilding", "TruthCampaign",
           "TruthElement", "TruthFacade", "build_city", "load_ply", "load_truth", "simulate"]
