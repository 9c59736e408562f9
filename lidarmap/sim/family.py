"""Scene families of the simulator and the seeds reserved for evaluation (docs/simulator.md).

* ``standard``: the scene the stages were developed on (lidarmap/sim/city.py);
* ``hard``: randomised on purpose (lidarmap/sim/hard.py), to judge façade extraction on scenes it was not tuned to.

Evaluation seeds (:data:`EVAL_SEEDS`) are reserved for benchmark figures: no development run, test or tuning
uses them (tests/test_sim.py checks that the test suite does not name them). Development uses :data:`DEV_SEEDS`.
"""

from __future__ import annotations

import dataclasses

from lidarmap.sim.city import City, build_city
from lidarmap.sim.hard import build_hard_city
from lidarmap.sim.params import SimParams

FAMILIES = ("standard", "hard")
EVAL_SEEDS = tuple(range(7001, 7251))  # 7011-7020 added 2026-11-26 after 7001-7010 had been measured three times;
#                                       7021-7030 added 2026-11-26 18:05 UTC, before any run, for round 7;
#                                       7031-7040 added 2026-11-26 20:46 UTC, before any run, for round 8;
#                                       7041-7050 added 2026-11-27 00:10 UTC, before any run, for round 9;
#                                       7051-7060 added 2026-11-28 16:47 UTC, before any run, for round 10;
#                                       7061-7070 added 2026-11-28 18:13 UTC, before any run, for the slab change;
#                                       7071-7080 added 2026-11-29 03:08 UTC, before any run, for round 11;
#                                       7081-7090 added 2026-11-29 07:35 UTC, before any run, for round 12;
#                                       7091-7100 added 2026-11-29 10:03 UTC, before any run, for round 13;
#                                       7101-7110 added 2026-11-29 12:29 UTC, before any run, for round 14;
#                                       7111-7120 added 2026-11-29 14:40 UTC, before any run, for round 15;
#                                       7121-7130 added 2026-11-29 17:22 UTC, before any run, for round 16;
#                                       7131-7140 added 2026-11-29 19:13 UTC, before any run, for round 17;
#                                       7141-7150 added 2026-11-29 21:59 UTC, before any run, for round 18;
#                                       7151-7160 added 2026-12-02 00:15 UTC, before any run, for round 20;
#                                       7161-7170 added 2026-12-02 04:24 UTC, before any run, for round 21;
#                                       7171-7180 added 2026-12-02 12:59 UTC, before any run, for round 22;
#                                       7181-7190 added 2026-12-02 16:55 UTC, before any run, for round 23;
#                                       7191-7200 added 2026-12-02 19:14 UTC, before any run, for round 24;
#                                       7201-7210 added 2026-12-02 21:44 UTC, before any run, for round 25;
#                                       7211-7220 added 2026-12-03 05:43 UTC, before any run, for round 26;
#                                       7221-7230 added 2026-12-03 07:57 UTC, before any run, for round 27;
#                                       7231-7240 added 2026-12-03 11:18 UTC, before any run, for round 28;
#                                       7241-7250 added 2026-12-03 14:48 UTC, before any run, for round 29
DEV_SEEDS = (11, 12, 13)


def build_family_city(params: SimParams) -> City:
    """The city of ``params`` in its family."""
    return build_hard_city(params) if params.family == "hard" else build_city(params)


def family_params(family: str, seed: int, **overrides) -> SimParams:
    """Parameters of one scene of ``family`` (defaults of :class:`SimParams` otherwise)."""
    return dataclasses.replace(SimParams(family=family, seed=seed), **overrides)


def seeds(evaluation: bool, count: int) -> list[int]:
    """The first ``count`` evaluation seeds (benchmark figures) or development seeds (anything else)."""
    pool = EVAL_SEEDS if evaluation else DEV_SEEDS
    if not 1 <= count <= len(pool):
        raise ValueError(f"count must be in [1, {len(pool)}] for {'evaluation' if evaluation else 'development'} seeds")
    return list(pool[:count])
