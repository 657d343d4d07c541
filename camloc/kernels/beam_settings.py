"""The beam's fixed constants (not options): see ``docs/beam.md`` for each one's reason."""

# Hypotheses whose states differ by less than this many standard deviations on every axis merge.
MERGE_SIGMA = 0.3
# Most partial explanations of a pose kept across all the beam's hypotheses, past each one's best.
PARTIAL_BUDGET = 64
# A conditioned hypothesis re-gates an observation among the landmarks within this many gates before.
POOL_GATE_FACTOR = 2.0
# The slip's search runs at a pose of at least this many observations, most of them unassigned: two
# detections with depth pin the position and two of the three rotation axes, with the prior the third.
SLIP_MIN_OBSERVATIONS = 2
# The slip's search: pairs ranked as first pairs, seeds explained in full, explanations kept per seed.
SLIP_CANDIDATES = 256
SLIP_SEEDS = 8
SEED_EXPLANATIONS = 2
# What an explanation pays for each landmark near a pixel observation's ray, surely within its camera's
# detection range, that it leaves unclaimed (``camloc.beam.BeamSearch._expected``, ``_missed``).
MISS_COST = 8.0
