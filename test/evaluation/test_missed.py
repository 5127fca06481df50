"""Why the node did not publish a revisit: each cause, constructed."""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation.missed import MISSED_REASONS, missed_revisits
from vbrl_ros.evaluation.verified import Candidates, VerifiedCandidates

# database keyframes 0-9 along x, 10 m apart; each query stands beside one of them
DATABASE = np.column_stack([np.arange(10) * 10.0, np.zeros(10), np.zeros(10)])


def verified(fitness, rejection) -> VerifiedCandidates:
    fitness = np.array(fitness, dtype=float)
    return VerifiedCandidates(fitness, np.array(rejection, dtype=object), np.full((*fitness.shape, 4, 4), np.nan))


def test_each_missed_revisit_is_put_down_to_the_cause_nearest_to_publishing():
    # query k stands 1 m from keyframe k; candidates: the right keyframe and/or wrong ones
    queries = DATABASE[:8] + [0.0, 1.0, 0.0]
    candidates = Candidates(np.array([[0, 5, -1],   # published right
                                      [5, 6, -1],   # a wrong one published
                                      [5, 6, -1],   # the right one not among them
                                      [9, 3, -1],   # right: passed but for the fitness
                                      [4, 9, -1],   # right: degenerate (and the wrong one too low)
                                      [5, -1, -1],  # right: too far
                                      [6, 9, -1],   # right: not converged
                                      [7, 9, -1]]),  # right: both below and degenerate -> below
                            np.ones((8, 3)))
    check = verified([[0.5, 0.1, np.nan], [0.5, 0.1, np.nan], [0.1, 0.1, np.nan], [0.1, 0.15, np.nan],
                      [0.3, 0.1, np.nan], [0.3, np.nan, np.nan], [np.nan, 0.1, np.nan], [0.1, 0.3, np.nan]],
                     [[None, None, "no candidate"], [None, None, "no candidate"], [None, None, "no candidate"],
                      [None, None, "no candidate"], ["degenerate", "low fitness", "no candidate"],
                      ["too far", "no candidate", "no candidate"], ["not converged", None, "no candidate"],
                      ["low fitness", None, "no candidate"]])
    published = np.array([[0], [5], [-1], [-1], [-1], [-1], [-1], [-1]])
    counts = missed_revisits(queries, DATABASE, None, candidates, check, published, radius=3.0, min_fitness=0.2)
    assert list(counts) == list(MISSED_REASONS)
    assert counts == {"wrong place": 1, "no right candidate": 1, "below min_fitness": 2, "degenerate": 1,
                      "too far": 1, "other": 1}
    # a keyframe out of sight (P1's excluded recent ones) makes no revisit and no miss
    limits = np.array([10, 10, 10, 10, 10, 10, 10, 7])
    assert sum(missed_revisits(queries, DATABASE, limits, candidates, check, published, 3.0, 0.2).values()) == 6


def test_a_candidate_that_passed_yet_was_not_published_is_not_blamed_on_the_fitness():
    queries = DATABASE[:1] + [0.0, 1.0, 0.0]
    counts = missed_revisits(queries, DATABASE, None, Candidates(np.array([[0]]), np.ones((1, 1))),
                             verified([[0.6]], [[None]]), np.array([[-1]]), radius=3.0, min_fitness=0.2)
    assert counts["other"] == 1 and counts["below min_fitness"] == 0
